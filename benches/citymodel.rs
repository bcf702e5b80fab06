//! Benchmark of the citymodel stage on the real 27-building street block (20 MB of CityGML):
//! parse throughput, triangulation time against the CGAL reference script on the same
//! polygons (same run), and peak memory. Run: `cargo bench --bench citymodel`.
use std::path::{Path, PathBuf};
use std::time::Instant;

use gs4city::{citygml, citymodel};

fn files() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/citygml/ingolstadt_north");
    let mut f: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .map(|d| d.join(format!("{}.gml", d.file_name().unwrap().to_string_lossy())))
        .collect();
    f.sort();
    f
}

fn best_of<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..n {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.expect("n > 0"))
}

fn peak_rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn main() {
    let files = files();
    let bytes: u64 = files
        .iter()
        .map(|f| std::fs::metadata(f).map(|m| m.len()).unwrap_or(0))
        .sum();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");

    // Parse only, one thread, sequential over files.
    let (t_parse, models) = best_of(3, || {
        files
            .iter()
            .map(|f| citygml::read(f).expect("read"))
            .collect::<Vec<_>>()
    });
    let polys: usize = models.iter().map(|m| m.polygons.len()).sum();
    println!(
        "parse (1 thread): {:.3} s for {:.1} MB → {:.1} MB/s, {polys} patches",
        t_parse,
        bytes as f64 / 1e6,
        bytes as f64 / 1e6 / t_parse
    );

    // Triangulate every patch (used or not), one thread — the same polygons as the CGAL script.
    let (t_tri, n_tri) = best_of(3, || {
        one.install(|| {
            models
                .iter()
                .map(|m| {
                    citymodel::triangulate_all(m)
                        .iter()
                        .filter_map(|r| r.result.as_ref().ok().map(|x| x.0))
                        .sum::<usize>()
                })
                .sum::<usize>()
        })
    });
    println!(
        "triangulate (1 thread, spade): {:.3} s, {n_tri} triangles, {:.0} patches/s",
        t_tri,
        polys as f64 / t_tri
    );

    // Whole stage (parse + flatten + triangulate + align), all threads.
    let (t_stage, out) = best_of(3, || {
        citymodel::run(&files, &Default::default()).expect("stage")
    });
    println!(
        "citymodel stage (rayon, {} threads): {:.3} s, {} triangles",
        rayon::current_num_threads(),
        t_stage,
        out.mesh.faces.len()
    );

    // Peer: the CGAL script on the same files (its own timer around CDT + face filter only).
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/cgal_reference.py");
    let tmp = std::env::temp_dir().join(format!("gs4city-bench-cgal-{}", std::process::id()));
    let status = std::process::Command::new("python3")
        .arg(&script)
        .arg("--out")
        .arg(&tmp)
        .args(&files)
        .output();
    match status {
        Ok(o) if o.status.success() => {
            let mut t_cgal = 0.0;
            for f in &files {
                let stem = f.file_stem().unwrap().to_string_lossy();
                let j: serde_json::Value = serde_json::from_slice(
                    &std::fs::read(tmp.join(format!("{stem}.json"))).expect("cgal json"),
                )
                .expect("json");
                t_cgal += j["seconds_triangulate"].as_f64().unwrap_or(f64::NAN);
            }
            println!(
                "triangulate (CGAL 2D CDT via Python, same patches): {:.3} s → spade/CGAL time ratio {:.2} (CGAL {:.1}× slower)",
                t_cgal,
                t_tri / t_cgal,
                t_cgal / t_tri
            );
        }
        Ok(o) => println!("CGAL peer failed: {}", String::from_utf8_lossy(&o.stderr)),
        Err(e) => println!("CGAL peer not run: {e}"),
    }
    let _ = std::fs::remove_dir_all(&tmp);
    println!(
        "peak memory (VmHWM, whole bench process): {:.1} MB",
        peak_rss_mb()
    );
}
