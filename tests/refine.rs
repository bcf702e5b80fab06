//! `refine`: robust 7-DoF ICP of Gaussian centres to the city-model mesh, on small hand-built
//! scenes with analytic answers (the true alignment is known because the scene is built from
//! it): recovery with noise and outliers, a perfectly aligned scene, the degenerate cases
//! (one façade, a street canyon), refusals, determinism across thread counts; and the
//! `gs4city align --refine` command on a synthetic scene.
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::{DMat3, DQuat, DVec3};
use gs4city::alignment::{Alignment, Similarity};
use gs4city::citygml::Level;
use gs4city::mesh::{FaceLabel, TriMesh};
use gs4city::refine::{self, RefineError, RefineInput, RefineOptions, RefineOutput};
use gs4city::semantics::Entity;
use gs4city::splat::Gaussians;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const ORIGIN: DVec3 = DVec3::new(678_000.0, 5_403_000.0, 400.0);

/// A planar quad in local metres (corners in order) and its CityGML surface class.
struct Quad {
    c: [DVec3; 4],
    class: &'static str,
}

/// A box building: footprint `w × d` centred at `(cx, cy)`, rotated by `yaw` degrees about z,
/// height `h`; four walls, a roof (flat, or a gable of height `gable` along the long side)
/// and a ground surface.
fn building(cx: f64, cy: f64, w: f64, d: f64, h: f64, yaw: f64, gable: f64) -> Vec<Quad> {
    let r = DMat3::from_rotation_z(yaw.to_radians());
    let p = |x: f64, y: f64, z: f64| DVec3::new(cx, cy, 0.0) + r * DVec3::new(x, y, z);
    let (a, b) = (w / 2.0, d / 2.0);
    let foot = [p(-a, -b, 0.0), p(a, -b, 0.0), p(a, b, 0.0), p(-a, b, 0.0)];
    let top = foot.map(|v| v + DVec3::Z * h);
    let mut q = Vec::new();
    for i in 0..4 {
        let j = (i + 1) % 4;
        q.push(Quad {
            c: [foot[i], foot[j], top[j], top[i]],
            class: "WallSurface",
        });
    }
    q.push(Quad {
        c: [foot[0], foot[3], foot[2], foot[1]],
        class: "GroundSurface",
    });
    if gable > 0.0 {
        // Ridge along x at y = 0; two slopes (the gable ends stay open: fine for a test).
        let ridge = [p(-a, 0.0, h + gable), p(a, 0.0, h + gable)];
        q.push(Quad {
            c: [top[0], top[1], ridge[1], ridge[0]],
            class: "RoofSurface",
        });
        q.push(Quad {
            c: [ridge[0], ridge[1], top[2], top[3]],
            class: "RoofSurface",
        });
    } else {
        q.push(Quad {
            c: [top[0], top[1], top[2], top[3]],
            class: "RoofSurface",
        });
    }
    q
}

/// Four buildings of different sizes and orientations.
fn town() -> Vec<Quad> {
    let mut q = building(10.0, 8.0, 16.0, 10.0, 9.0, 0.0, 0.0);
    q.extend(building(38.0, 6.0, 12.0, 9.0, 7.0, 0.0, 3.0));
    q.extend(building(14.0, 34.0, 10.0, 14.0, 12.0, 25.0, 0.0));
    q.extend(building(42.0, 32.0, 14.0, 8.0, 6.0, -40.0, 2.5));
    q
}

/// The mesh of `quads` aligned by `a` (f32, as the citymodel stage writes it) and its
/// entities (one surface entity per quad, one feature for all).
fn mesh(quads: &[Quad], a: &Alignment) -> (TriMesh, Vec<Entity>) {
    let mut m = TriMesh::default();
    let mut entities = vec![entity(0, "Building", Level::Feature, None)];
    for q in quads {
        let id = entities.len() as i32;
        entities.push(entity(id, q.class, Level::Surface, Some(0)));
        let l = FaceLabel {
            feature: 0,
            surface: id,
            part: -1,
        };
        let base = m.vertices.len() as u32;
        for v in q.c {
            let s = a.apply(ORIGIN + v);
            m.vertices.push([s.x as f32, s.y as f32, s.z as f32]);
        }
        m.faces.push([base, base + 1, base + 2]);
        m.faces.push([base, base + 2, base + 3]);
        m.labels.extend([l, l]);
    }
    (m, entities)
}

fn entity(id: i32, class: &str, level: Level, parent: Option<i32>) -> Entity {
    Entity {
        id,
        object_id: format!("e{id}"),
        class: gs4city::semantics::Class::from_local_name(class).unwrap(),
        level,
        parent,
        building: 0,
        source: "test".into(),
        lod: Some(3),
        attributes: Default::default(),
    }
}

/// How the simulated Gaussians deviate from the model.
#[derive(Clone, Copy)]
struct Corruption {
    /// σ of the offset along the surface normal, m.
    noise_m: f64,
    /// Fraction of wall samples recessed 0.15 m into the building (like windows).
    recessed: f64,
    /// Flat floaters of random orientation near the buildings, as a fraction of the samples.
    floaters: f64,
    /// A ground plane at z = 0 (not in the model).
    ground: bool,
}

const CLEAN: Corruption = Corruption {
    noise_m: 0.0,
    recessed: 0.0,
    floaters: 0.0,
    ground: false,
};

const DIRTY: Corruption = Corruption {
    noise_m: 0.01,
    recessed: 0.1,
    floaters: 0.15,
    ground: true,
};

/// Pushes one Gaussian: centre `p` and frame `(t1, t2, n)` in local metres, mapped to the
/// scene by `a`; in-plane σ 0.08 m, thickness `thick` (both × scale).
fn push(g: &mut Gaussians, a: &Alignment, p: DVec3, frame: DMat3, thick: f64, opacity: f32) {
    let s = a.apply(ORIGIN + p);
    g.positions.push([s.x as f32, s.y as f32, s.z as f32]);
    let q = DQuat::from_mat3(&(a.rotation * frame)).normalize();
    g.rotation
        .push([q.w as f32, q.x as f32, q.y as f32, q.z as f32]);
    let k = a.scale;
    g.scale.push([
        (0.08 * k).ln() as f32,
        (0.08 * k).ln() as f32,
        (thick * k).ln() as f32,
    ]);
    g.opacity.push(opacity);
    g.f_dc.push([0.5, 0.5, 0.5]);
}

fn frame_of(n: DVec3) -> DMat3 {
    let t1 = if n.z.abs() < 0.9 {
        DVec3::Z.cross(n)
    } else {
        DVec3::X.cross(n)
    }
    .normalize();
    DMat3::from_cols(t1, n.cross(t1), n)
}

/// Gaussians sampled on the visible quads (walls, roofs) at `density` per m², in the scene
/// frame of the TRUE alignment `a`, plus the corruption, plus non-flat and transparent
/// Gaussians that the selection must drop.
fn gaussians(quads: &[Quad], a: &Alignment, density: f64, c: Corruption, seed: u64) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians::default();
    let mut samples = 0usize;
    for q in quads.iter().filter(|q| q.class != "GroundSurface") {
        let (u, v) = (q.c[1] - q.c[0], q.c[3] - q.c[0]);
        let n = u.cross(v).normalize();
        let area = u.cross(v).length(); // parallelograms (our quads are)
        let count = (area * density).round() as usize;
        let inward = if q.class == "WallSurface" {
            -n
        } else {
            DVec3::ZERO
        };
        for _ in 0..count {
            let mut p = q.c[0] + rng.random::<f64>() * u + rng.random::<f64>() * v;
            p += n * gauss(&mut rng) * c.noise_m;
            if rng.random::<f64>() < c.recessed {
                p += inward * 0.15;
            }
            push(&mut g, a, p, frame_of(n), 0.005, 3.0);
            samples += 1;
        }
    }
    let lo = DVec3::new(-5.0, -5.0, 0.0);
    let hi = DVec3::new(55.0, 50.0, 15.0);
    let floaters = (samples as f64 * c.floaters) as usize;
    for _ in 0..floaters {
        let p = lo + (hi - lo) * DVec3::new(rng.random(), rng.random(), rng.random());
        let n = DVec3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)).normalize();
        push(&mut g, a, p, frame_of(n), 0.005, 2.0);
    }
    if c.ground {
        for _ in 0..(60.0 * 55.0 * density * 0.3) as usize {
            let p = DVec3::new(
                rng.random_range(-5.0..55.0),
                rng.random_range(-5.0..50.0),
                0.0,
            );
            push(&mut g, a, p, frame_of(DVec3::Z), 0.005, 3.0);
        }
    }
    // Trees (isotropic blobs) and transparent haze: never selected.
    for _ in 0..2000 {
        let p = lo + (hi - lo) * DVec3::new(rng.random(), rng.random(), rng.random());
        push(&mut g, a, p, DMat3::IDENTITY, 0.08, 3.0);
        push(&mut g, a, p, frame_of(DVec3::X), 0.005, -4.0);
    }
    g
}

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    // Box–Muller.
    let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// The true alignment of the tests: rotated 37° about z, scale 0.8, a far translation.
fn truth() -> Alignment {
    Alignment {
        origin: ORIGIN,
        scale: 0.8,
        rotation: DMat3::from_rotation_z(37f64.to_radians()),
        translation: DVec3::new(1200.0, -800.0, 35.0),
    }
}

/// `a` perturbed about the scene point of local `centre`: rotation `deg` about `axis`,
/// translation `t_m` metres along `dir`, relative scale error `ds`.
fn perturb(
    a: &Alignment,
    centre: DVec3,
    deg: f64,
    axis: DVec3,
    t_m: f64,
    dir: DVec3,
    ds: f64,
) -> Alignment {
    let c = a.apply(ORIGIN + centre);
    let r = DMat3::from_axis_angle(axis.normalize(), deg.to_radians());
    let e = 1.0 + ds;
    let s = Similarity {
        scale: e,
        rotation: r,
        translation: c - e * (r * c) + dir.normalize() * t_m * a.scale,
    };
    a.then(&s)
}

/// The test's own score of alignment `got` against `want` (written from the alignment's
/// definition `x = s·R·(p − o) + t`, without `refine::compare`, `Alignment::apply` or
/// `Alignment::relative`): over the vertices `verts` (scene coordinates of alignment `frame`,
/// mapped back to geo coordinates by the closed-form inverse), the RMS and max distance between
/// where `want` and `got` put each point, in metres of `want`'s scale; the rotation angle between
/// the two rotations from the trace of `R_got·R_wantᵀ`; and the relative scale error in percent.
#[derive(Debug, Clone, Copy)]
struct Score {
    rms_m: f64,
    max_m: f64,
    rotation_deg: f64,
    scale_pct: f64,
}

fn score(want: &Alignment, got: &Alignment, verts: &[[f32; 3]], frame: &Alignment) -> Score {
    let place = |a: &Alignment, p: DVec3| {
        let d = p - a.origin;
        let r = a.rotation;
        // Row by row: (R·d)_i = Σ_j R_ij d_j, with R_ij = r.col(j)[i].
        let rd = DVec3::new(
            r.x_axis.x * d.x + r.y_axis.x * d.y + r.z_axis.x * d.z,
            r.x_axis.y * d.x + r.y_axis.y * d.y + r.z_axis.y * d.z,
            r.x_axis.z * d.x + r.y_axis.z * d.y + r.z_axis.z * d.z,
        );
        rd * a.scale + a.translation
    };
    let geo = |v: &[f32; 3]| {
        // p = o + Rᵀ·(x − t)/s: (Rᵀ·y)_i = Σ_j R_ji y_j = column i of R dotted with y.
        let y = (DVec3::from_array(v.map(f64::from)) - frame.translation) / frame.scale;
        let r = frame.rotation;
        frame.origin + DVec3::new(r.x_axis.dot(y), r.y_axis.dot(y), r.z_axis.dot(y))
    };
    let (mut sum2, mut max) = (0.0f64, 0.0f64);
    for v in verts {
        let p = geo(v);
        let d = (place(got, p) - place(want, p)).length() / want.scale;
        sum2 += d * d;
        max = max.max(d);
    }
    let q = got.rotation * want.rotation.transpose();
    let trace = q.x_axis.x + q.y_axis.y + q.z_axis.z;
    Score {
        rms_m: (sum2 / verts.len() as f64).sqrt(),
        max_m: max,
        rotation_deg: ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees(),
        scale_pct: (got.scale / want.scale - 1.0) * 100.0,
    }
}

fn run(
    quads: &[Quad],
    given: &Alignment,
    g: &Gaussians,
    opts: &RefineOptions,
) -> (Result<RefineOutput, RefineError>, TriMesh) {
    let (m, e) = mesh(quads, given);
    let input = RefineInput {
        mesh: &m,
        entities: &e,
        initial: given,
        gaussians: g,
        camera_centres: None,
    };
    (refine::refine(&input, opts), m)
}

#[test]
fn recovers_a_similarity_with_noise_and_outliers() {
    let quads = town();
    let t = truth();
    let g = gaussians(&quads, &t, 25.0, DIRTY, 1);
    let centre = DVec3::new(25.0, 20.0, 5.0);
    for (k, (deg, tm, ds)) in [(0.5, 0.3, 0.0), (2.0, 0.8, 0.015), (1.0, 1.5, -0.01)]
        .into_iter()
        .enumerate()
    {
        let given = perturb(
            &t,
            centre,
            deg,
            DVec3::new(0.3, -0.5, 1.0),
            tm,
            DVec3::new(1.0, 2.0, -0.5),
            ds,
        );
        let (out, m) = run(&quads, &given, &g, &RefineOptions::default());
        let out = out.unwrap_or_else(|e| panic!("case {k}: {e}"));
        let before = score(&t, &given, &m.vertices, &given);
        let err = score(&t, &out.alignment, &m.vertices, &given);
        assert!(
            before.rms_m > 0.25,
            "case {k}: the perturbation is real: {before:?}"
        );
        // 1 cm noise over ~40k samples, 10 % recessed, 15 % floaters, a ground plane.
        eprintln!(
            "case {k}: before {before:?}\n  after {err:?}\n  iterations {}",
            out.iterations
        );
        assert!(err.rms_m < 0.005, "case {k}: {err:?}");
        // (an angle from the trace resolves ≈ 1e-6° near 0: enough for a 0.01° bound)
        assert!(err.rotation_deg < 0.01, "case {k}: {err:?}");
        assert!(err.scale_pct.abs() < 0.05, "case {k}: {err:?}");
        assert!(out.converged);
        // The stage's own correction report is how far its result moved the mesh from the
        // given alignment (the test's score of `out` against `given`, in metres of the given
        // scale), and about as far as the applied perturbation (metres of the given scale vs
        // of the true scale: equal within the scale error).
        let moved = score(&given, &out.alignment, &m.vertices, &given);
        assert!(
            (out.correction.rms_m - moved.rms_m).abs() < 1e-9 * moved.rms_m
                && (out.correction.max_m - moved.max_m).abs() < 1e-9 * moved.max_m,
            "case {k}: {:?} vs {moved:?}",
            out.correction
        );
        let rel = (out.correction.rms_m - before.rms_m).abs() / before.rms_m;
        assert!(rel < 0.02, "case {k}: {:?} vs {before:?}", out.correction);
        assert!(
            out.after.median_m < 0.01 && out.before.median_m > 0.05,
            "case {k}"
        );
        assert!(out.after.within_2cm > 0.6, "case {k}: {:?}", out.after);
        // Ground surfaces (one quad = 2 triangles per building) are not targets.
        assert_eq!(out.selection.excluded_triangles, 8);
        // Trees and haze are not selected; everything else is (no voxel collisions at
        // this density with 0.25 m voxels is not guaranteed, so only bound it).
        assert_eq!(out.selection.opaque, g.len() - 2000);
        assert_eq!(out.selection.opaque_flat, g.len() - 4000);
        assert!(out.conditioning.ratio > 1e-2, "{:?}", out.conditioning);
    }
}

/// A pure height error: the walls (most of the surface) fit at once and say nothing about
/// the height; only the roofs, still 2 m off, fix it. (Found on the street scene: a
/// robust scale set by the walls turned the roofs into outliers before they had moved.)
#[test]
fn roofs_fix_the_height_although_walls_dominate() {
    let quads = town();
    let t = truth();
    let g = gaussians(&quads, &t, 25.0, DIRTY, 8);
    for dz in [2.0, -2.5] {
        let given = perturb(
            &t,
            DVec3::new(25.0, 20.0, 5.0),
            0.0,
            DVec3::Z,
            dz,
            DVec3::Z,
            0.0,
        );
        let (out, m) = run(&quads, &given, &g, &RefineOptions::default());
        let out = out.unwrap();
        let err = score(&t, &out.alignment, &m.vertices, &given);
        assert!(err.rms_m < 0.005, "dz {dz}: {err:?}");
    }
}

#[test]
fn a_perfectly_aligned_scene_does_not_move() {
    let quads = town();
    let t = truth();
    let g = gaussians(&quads, &t, 25.0, DIRTY, 2);
    let (out, m) = run(&quads, &t, &g, &RefineOptions::default());
    let out = out.unwrap();
    let moved = score(&t, &out.alignment, &m.vertices, &t);
    assert!(moved.rms_m < 0.002 && moved.max_m < 0.005, "{moved:?}");
    // The stage's correction report: the same displacement, computed by the test.
    assert!(
        (out.correction.rms_m - moved.rms_m).abs() <= 1e-9 * moved.rms_m.max(1e-12)
            && (out.correction.max_m - moved.max_m).abs() <= 1e-9 * moved.max_m.max(1e-12),
        "{:?} vs {moved:?}",
        out.correction
    );
    // Noise-free: exact up to f32 storage of the inputs.
    let g = gaussians(&quads, &t, 25.0, CLEAN, 2);
    let (out, m) = run(&quads, &t, &g, &RefineOptions::default());
    let moved = score(&t, &out.unwrap().alignment, &m.vertices, &t);
    assert!(moved.max_m < 2e-4, "{moved:?}");
}

#[test]
fn rigid_mode_keeps_the_scale() {
    let quads = town();
    let t = truth();
    let g = gaussians(&quads, &t, 25.0, DIRTY, 3);
    let given = perturb(
        &t,
        DVec3::new(25.0, 20.0, 5.0),
        0.5,
        DVec3::Z,
        0.3,
        DVec3::X,
        0.0,
    );
    let opts = RefineOptions {
        estimate_scale: false,
        ..Default::default()
    };
    let (out, m) = run(&quads, &given, &g, &opts);
    let out = out.unwrap();
    assert_eq!(out.alignment.scale.to_bits(), given.scale.to_bits());
    let err = score(&t, &out.alignment, &m.vertices, &given);
    assert!(err.rms_m < 0.005, "{err:?}");
}

#[test]
fn a_single_facade_is_refused_as_ambiguous() {
    let wall = vec![Quad {
        c: [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(30.0, 0.0, 0.0),
            DVec3::new(30.0, 0.0, 10.0),
            DVec3::new(0.0, 0.0, 10.0),
        ],
        class: "WallSurface",
    }];
    let t = truth();
    let g = gaussians(
        &wall,
        &t,
        25.0,
        Corruption {
            noise_m: 0.01,
            ..CLEAN
        },
        4,
    );
    let given = perturb(
        &t,
        DVec3::new(15.0, 0.0, 5.0),
        0.2,
        DVec3::Z,
        0.2,
        DVec3::Y,
        0.0,
    );
    let (out, _) = run(&wall, &given, &g, &RefineOptions::default());
    match out {
        Err(e @ RefineError::Degenerate { ratio, .. }) => {
            assert!(ratio < 1e-6, "{ratio}");
            let msg = e.to_string();
            assert!(
                msg.contains("ambiguous") && msg.contains("single façade"),
                "{msg}"
            );
        }
        other => panic!("expected a refusal, got {:?}", other.map(|o| o.alignment)),
    }
}

#[test]
fn a_street_canyon_without_cross_walls_is_refused() {
    // Two parallel façades along x: nothing fixes the translation along x (or z).
    let wall = |y: f64| Quad {
        c: [
            DVec3::new(0.0, y, 0.0),
            DVec3::new(60.0, y, 0.0),
            DVec3::new(60.0, y, 12.0),
            DVec3::new(0.0, y, 12.0),
        ],
        class: "WallSurface",
    };
    let quads = vec![wall(0.0), wall(15.0)];
    let t = truth();
    let g = gaussians(
        &quads,
        &t,
        20.0,
        Corruption {
            noise_m: 0.01,
            ..CLEAN
        },
        5,
    );
    let given = perturb(
        &t,
        DVec3::new(30.0, 7.5, 6.0),
        0.3,
        DVec3::Z,
        0.2,
        DVec3::Y,
        0.0,
    );
    let (out, _) = run(&quads, &given, &g, &RefineOptions::default());
    let Err(RefineError::Degenerate { weakest, .. }) = out else {
        panic!("expected Degenerate");
    };
    // The weakest direction is an x/z translation or the rotation about y (the wall normal
    // is ±y in the local frame, rotated 37° about z in the scene).
    assert!(
        weakest.contains("translation") || weakest.contains("rotation"),
        "{weakest}"
    );
}

#[test]
fn refusals_name_the_reason() {
    let quads = town();
    let t = truth();
    // Far outside the basin: 20 m off, nothing within the 3 m search radius.
    let g = gaussians(&quads, &t, 10.0, CLEAN, 6);
    let given = perturb(&t, DVec3::ZERO, 0.0, DVec3::Z, 20.0, DVec3::Z, 0.0);
    let (out, _) = run(&quads, &given, &g, &RefineOptions::default());
    let e = out.expect_err("refused");
    assert!(matches!(e, RefineError::TooFewMatches { .. }), "{e}");
    assert!(e.to_string().contains("3.000 m"), "{e}");
    // Only transparent Gaussians.
    let mut haze = g.clone();
    haze.opacity.iter_mut().for_each(|o| *o = -5.0);
    let (out, _) = run(&quads, &t, &haze, &RefineOptions::default());
    assert!(matches!(
        out,
        Err(RefineError::TooFewGaussians { selected: 0, .. })
    ));
    // Bad options.
    for bad in [
        RefineOptions {
            voxel_m: 0.0,
            ..Default::default()
        },
        RefineOptions {
            initial_radius_m: f64::NAN,
            ..Default::default()
        },
        RefineOptions {
            final_radius_m: 5.0,
            ..Default::default()
        },
    ] {
        let (out, _) = run(&quads, &t, &g, &bad);
        assert!(matches!(out, Err(RefineError::Options(_))));
    }
    // An iteration cap too low to converge is an error, not a silent result.
    let given = perturb(
        &t,
        DVec3::new(25.0, 20.0, 5.0),
        1.0,
        DVec3::Z,
        0.5,
        DVec3::X,
        0.0,
    );
    let opts = RefineOptions {
        max_iterations: 2,
        ..Default::default()
    };
    let (out, _) = run(&quads, &given, &g, &opts);
    assert!(
        matches!(out, Err(RefineError::NotConverged { iterations: 2, .. })),
        "{out:?}"
    );
}

#[test]
fn same_result_with_one_and_two_threads() {
    let quads = town();
    let t = truth();
    let g = gaussians(&quads, &t, 20.0, DIRTY, 7);
    let given = perturb(
        &t,
        DVec3::new(25.0, 20.0, 5.0),
        1.0,
        DVec3::new(1.0, 1.0, 1.0),
        0.5,
        DVec3::Y,
        0.01,
    );
    let once = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            run(&quads, &given, &g, &RefineOptions::default())
                .0
                .unwrap()
        })
    };
    let (a, b) = (once(1), once(2));
    assert_eq!(
        a.alignment.to_json().to_string(),
        b.alignment.to_json().to_string()
    );
    assert_eq!(a.iterations, b.iterations);
    assert_eq!(a.after, b.after);
}

fn gs4city(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .output()
        .expect("run gs4city");
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

fn read_alignment(v: &serde_json::Value) -> Alignment {
    Alignment::from_json_str(Path::new("summary.json"), &v.to_string()).unwrap()
}

/// `align --refine` on the SIMULATED small preset (2 real buildings) with a 0.3 m / 0.5° /
/// 1 % alignment error: the written alignment is close to the truth in the scene's
/// summary.json (read here only, to score); summary.json lands beside it; the folder's
/// own files are never overwritten.
#[test]
fn cli_refines_a_synthetic_scene() {
    let dir = crate::common::temp_dir().join(format!("gs4city-refine-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("noise.toml");
    std::fs::write(
        &cfg,
        "[noise]\ntranslation_m = 0.3\nrotation_deg = 0.5\nscale = 0.01\n[cameras]\norbit_views = 2\nstreet_views = 0\n",
    )
    .unwrap();
    let scene = dir.join("scene");
    let s = |p: &PathBuf| p.to_str().unwrap().to_string();
    let (ok, log) = gs4city(&[
        "synth",
        "--preset",
        "small",
        "--config",
        &s(&cfg),
        "--out",
        &s(&scene),
    ]);
    assert!(ok, "{log}");
    let out = dir.join("refined/alignment.json");
    let args = |out: &PathBuf| {
        vec![
            "align".to_string(),
            "--refine".into(),
            "--citymodel".into(),
            s(&scene.join("citymodel")),
            "--ply".into(),
            s(&scene.join("point_cloud.ply")),
            "--colmap".into(),
            s(&scene.join("sparse/0")),
            "--out".into(),
            s(out),
        ]
    };
    let a: Vec<String> = args(&out);
    let (ok, log) = gs4city(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{log}");
    assert!(log.contains("converged"), "{log}");
    let truth_json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("summary.json")).unwrap())
            .unwrap();
    let t = read_alignment(&truth_json["alignment_true"]);
    let given = read_alignment(&truth_json["alignment_given"]);
    let refined = Alignment::read(&out).unwrap();
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("refined/summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["stage"], "align_refine");
    // (equal up to serde_json's float parsing, which is not always correctly rounded)
    let in_summary = read_alignment(&summary["alignment"]);
    let g = t.origin + DVec3::new(30.0, 20.0, 10.0);
    assert!((in_summary.apply(g) - refined.apply(g)).length() < 1e-9);
    // Score on a grid of points over the two buildings' extent (local metres 0..60).
    let mut verts = Vec::new();
    for i in 0..10 {
        for j in 0..10 {
            for k in 0..3 {
                let geo = t.origin + DVec3::new(i as f64 * 6.0, j as f64 * 6.0, k as f64 * 8.0);
                let p = given.apply(geo);
                verts.push([p.x as f32, p.y as f32, p.z as f32]);
            }
        }
    }
    let before = score(&t, &given, &verts, &given);
    let err = score(&t, &refined, &verts, &given);
    assert!(before.rms_m > 0.3, "{before:?}");
    assert!(
        err.rms_m < 0.03 && err.rotation_deg < 0.05 && err.scale_pct.abs() < 0.2,
        "{err:?}"
    );
    // A second run overwrites its own summary.json; a foreign summary.json is refused, and
    // so is writing over the input alignment.
    let (ok, log) = gs4city(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{log}");
    let foreign = scene.join("alignment.json"); // beside the scene's own summary.json
    let (ok, log) = gs4city(
        &args(&foreign)
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    assert!(!ok && log.contains("refusing to overwrite"), "{log}");
    let input = scene.join("citymodel/alignment.json");
    let (ok, log) = gs4city(&args(&input).iter().map(String::as_str).collect::<Vec<_>>());
    assert!(!ok && log.contains("input alignment"), "{log}");
    // Refine options from the config file's [refine] section: unknown keys are errors naming
    // the file and the line.
    let bad = dir.join("opts.toml");
    std::fs::write(&bad, "[refine]\nvoxel_m = 0.5\nvoxel = 1\n").unwrap();
    let mut with_opts = args(&out);
    with_opts.extend(["--config".to_string(), s(&bad)]);
    let (ok, log) = gs4city(&with_opts.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(
        !ok && log.contains("opts.toml:3") && log.contains("voxel"),
        "{log}"
    );
    // Point-pair mode still works, and the two modes exclude each other.
    let csv = dir.join("pairs.csv");
    std::fs::write(&csv, "0 0 0 1 1 1\n1 0 0 2 1 1\n0 1 0 1 2 1\n0 0 1 1 1 2\n").unwrap();
    let pairs_out = dir.join("pairs/alignment.json");
    std::fs::create_dir_all(pairs_out.parent().unwrap()).unwrap();
    let (ok, log) = gs4city(&["align", "--points", &s(&csv), "--out", &s(&pairs_out)]);
    assert!(ok, "{log}");
    let (ok, _) = gs4city(&[
        "align",
        "--points",
        &s(&csv),
        "--refine",
        "--out",
        &s(&pairs_out),
    ]);
    assert!(!ok);
    let _ = std::fs::remove_dir_all(&dir);
}
