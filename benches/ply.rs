//! PLY throughput: the 3DGS splat PLY (1M Gaussians, SH degree 3, 62 float properties,
//! binary little-endian; the general decoding path; ASCII on 100k) and the city mesh PLY
//! (1M triangles with labels). `cargo bench --bench ply`; every time is the best of N
//! repetitions with the file in the page cache (the time includes reading the file).
use std::path::Path;
use std::time::Instant;

use gs4city::mesh::{FaceLabel, TriMesh};
use gs4city::splat::{Gaussians, PlyEncoding, ReadOptions, read_ply, write_ply};
use rand::{Rng, SeedableRng};

fn gaussians(n: usize, seed: u64) -> Gaussians {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians {
        sh_degree: 3,
        normals: Some(Vec::with_capacity(n)),
        ..Default::default()
    };
    for _ in 0..n {
        let mut r = |a: f32, b: f32| rng.random_range(a..b);
        g.positions
            .push([r(-50.0, 50.0), r(-50.0, 50.0), r(0.0, 20.0)]);
        g.normals.as_mut().unwrap().push([0.0; 3]);
        g.f_dc.push([r(-1.0, 1.0), r(-1.0, 1.0), r(-1.0, 1.0)]);
        for _ in 0..45 {
            g.f_rest.push(r(-0.1, 0.1));
        }
        g.opacity.push(r(-4.0, 4.0));
        g.scale.push([r(-6.0, -1.0), r(-6.0, -1.0), r(-6.0, -1.0)]);
        g.rotation
            .push([r(0.5, 1.0), r(-1.0, 1.0), r(-1.0, 1.0), r(-1.0, 1.0)]);
    }
    g
}

fn mesh(n_tri: usize) -> TriMesh {
    let side = ((n_tri / 2) as f64).sqrt().ceil() as u32;
    let mut m = TriMesh::default();
    for j in 0..=side {
        for i in 0..=side {
            m.vertices.push([i as f32, j as f32, ((i * j) % 7) as f32]);
        }
    }
    'outer: for j in 0..side {
        for i in 0..side {
            let a = j * (side + 1) + i;
            for f in [[a, a + 1, a + side + 2], [a, a + side + 2, a + side + 1]] {
                if m.faces.len() == n_tri {
                    break 'outer;
                }
                let k = m.faces.len() as i32;
                m.faces.push(f);
                m.labels.push(FaceLabel {
                    feature: k / 1000,
                    surface: k / 10,
                    part: if k % 3 == 0 { k } else { -1 },
                });
            }
        }
    }
    m
}

fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..reps {
        let t = Instant::now();
        let out = f();
        best = best.min(t.elapsed().as_secs_f64());
        last = Some(out);
    }
    (best, last.unwrap())
}

fn mb(p: &Path) -> f64 {
    std::fs::metadata(p).unwrap().len() as f64 / 1e6
}

fn main() {
    let dir = std::env::var_os("PLY_BENCH_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::env::temp_dir().join(format!("gs4city-plybench-{}", std::process::id()))
        });
    std::fs::create_dir_all(&dir).unwrap();
    println!("| what | file MB | best s | MB/s |");
    println!("|---|---:|---:|---:|");
    let row = |what: &str, mbytes: f64, s: f64| {
        println!("| {what} | {mbytes:.1} | {s:.3} | {:.0} |", mbytes / s);
    };

    let g = gaussians(1_000_000, 1);
    let bin = dir.join("splat1m.ply");
    let (s, ()) = best(3, || {
        write_ply(&bin, &g, PlyEncoding::BinaryLittleEndian).unwrap()
    });
    row("splat write, binary LE, 1M", mb(&bin), s);
    let (s, (back, _)) = best(5, || read_ply(&bin, &ReadOptions::default()).unwrap());
    assert_eq!(back.len(), g.len());
    row("splat read, binary LE fast path, 1M", mb(&bin), s);
    let general = ReadOptions {
        force_general_path: true,
        ..Default::default()
    };
    let (s, (back, _)) = best(1, || read_ply(&bin, &general).unwrap());
    assert_eq!(back.len(), g.len());
    row("splat read, general path, 1M", mb(&bin), s);
    drop(back);

    let g100k = gaussians(100_000, 2);
    let asc = dir.join("splat100k_ascii.ply");
    let (s, ()) = best(1, || write_ply(&asc, &g100k, PlyEncoding::Ascii).unwrap());
    row("splat write, ASCII, 100k", mb(&asc), s);
    let (s, (back, _)) = best(3, || read_ply(&asc, &ReadOptions::default()).unwrap());
    assert_eq!(back.len(), g100k.len());
    row("splat read, ASCII, 100k", mb(&asc), s);

    let m = mesh(1_000_000);
    let mp = dir.join("mesh1m.ply");
    let (s, ()) = best(3, || m.write_ply(&mp).unwrap());
    row("mesh write, 1M triangles", mb(&mp), s);
    let (s, back) = best(5, || TriMesh::read_ply(&mp).unwrap());
    assert_eq!(back, m);
    row("mesh read, 1M triangles", mb(&mp), s);
    if std::env::var_os("PLY_BENCH_DIR").is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    }
}
