//! The scene check and import, end to end on SIMULATED scenes (`synth --preset small`): `gs4city check` names each
//! defect of a scene in one line and `run` stops before any stage; a 3DGS training output
//! becomes a scene folder by `scene import` and runs; `run` resumes however `--scene` is spelled
//! and `query --run R` works from `/`; invalid Gaussians stay in `semantic.ply` labelled −1; a
//! class query's view masks are the class maps' pixels of that class.
use std::path::{Path, PathBuf};
use std::process::Command;

/// Runs the binary in `cwd` (default: the test's); `(success, stdout, stderr)`.
fn cli_in(cwd: Option<&Path>, args: &[&str]) -> (bool, String, String) {
    let mut c = Command::new(env!("CARGO_BIN_EXE_gs4city"));
    if let Some(d) = cwd {
        c.current_dir(d);
    }
    let out = c.args(args).output().expect("run gs4city");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A fresh folder for one test.
fn root(name: &str) -> PathBuf {
    let r = crate::common::temp_dir().join(format!("gs4city-check-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&r);
    std::fs::create_dir_all(&r).unwrap();
    r
}

/// `synth --preset small` into `dir`.
fn synth(dir: &Path) {
    let (ok, _, err) = cli_in(None, &["-q", "synth", "--preset", "small", "--out", s(dir)]);
    assert!(ok, "{err}");
}

fn copy_tree(src: &Path, dst: &Path) {
    if src.is_dir() {
        std::fs::create_dir_all(dst).unwrap();
        for e in std::fs::read_dir(src).unwrap() {
            let e = e.unwrap();
            copy_tree(&e.path(), &dst.join(e.file_name()));
        }
    } else {
        std::fs::copy(src, dst).unwrap();
    }
}

/// A variant of scene `base` at `dst`: the top-level parts in `copied` are copies (to be
/// changed), the others symbolic links.
fn variant(base: &Path, dst: &Path, copied: &[&str]) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(base).unwrap() {
        let e = e.unwrap();
        let name = e.file_name();
        if copied.iter().any(|c| name == *c) {
            copy_tree(&e.path(), &dst.join(&name));
        } else {
            std::os::unix::fs::symlink(e.path(), dst.join(&name)).unwrap();
        }
    }
}

/// Offset of the payload, vertex stride and offset of property `name` in a binary
/// little-endian all-float PLY (as `synth` writes).
fn ply_layout(bytes: &[u8], name: &str) -> (usize, usize, usize) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap();
    assert!(header.contains("format binary_little_endian 1.0"));
    let props: Vec<&str> = header
        .lines()
        .filter_map(|l| l.strip_prefix("property "))
        .collect();
    assert!(props.iter().all(|p| p.starts_with("float ")), "{props:?}");
    let at = props
        .iter()
        .position(|p| *p == format!("float {name}"))
        .unwrap();
    (end, props.len() * 4, at * 4)
}

/// Writes `value` into property `name` of vertex `vertex`.
fn set_property(ply: &Path, vertex: usize, name: &str, value: f32) {
    let mut b = std::fs::read(ply).unwrap();
    let (start, stride, off) = ply_layout(&b, name);
    let o = start + vertex * stride + off;
    b[o..o + 4].copy_from_slice(&value.to_le_bytes());
    std::fs::write(ply, b).unwrap();
}

/// The `error:` lines of a failed check, without the closing summary line.
fn error_lines(stderr: &str) -> Vec<&str> {
    stderr
        .lines()
        .filter(|l| l.starts_with("error: ") && !l.starts_with("error: check "))
        .collect()
}

#[test]
fn check_names_each_defect_in_one_line_and_run_stops_before_any_stage() {
    let r = root("defects");
    let base = r.join("base");
    synth(&base);
    let (ok, out, err) = cli_in(None, &["check", "--scene", s(&base)]);
    assert!(ok, "the simulated scene is fine: {err}");
    assert!(out.contains(": 0 errors, 0 warnings"), "{out}");
    assert!(err.contains("alignment plausible"), "{err}");

    let views = gs4city::colmap::read_model(&base.join("sparse/0")).unwrap();
    let (img, img_b) = (&views[3].name, &views[5].name);
    let align: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(base.join("citymodel/alignment.json")).unwrap(),
    )
    .unwrap();
    let scale = align["scale"].as_f64().unwrap();
    let n = gs4city::splat::read_ply(&base.join("point_cloud.ply"), &Default::default())
        .unwrap()
        .0
        .len();

    // (name, parts copied, the change, the one error line must contain these)
    type Change<'a> = Box<dyn Fn(&Path) + 'a>;
    let write_alignment = |d: &Path, f: &dyn Fn(&mut serde_json::Value)| {
        let mut a = align.clone();
        f(&mut a);
        let p = d.join("citymodel/alignment.json");
        std::fs::write(p, serde_json::to_string_pretty(&a).unwrap()).unwrap();
    };
    let img1 = img.clone();
    let img2 = img_b.clone();
    let stem = views[2].stem();
    let (stem1, stem2) = (stem.clone(), stem.clone());
    let gml_name = std::fs::read_dir(base.join("citymodel"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "gml"))
        .min()
        .unwrap()
        .file_name()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    let gml1 = gml_name.clone();
    let cases: Vec<(&str, Vec<&str>, Change<'_>, Vec<String>)> = vec![
        (
            "missing-image",
            vec!["images"],
            Box::new(move |d: &Path| std::fs::remove_file(d.join("images").join(&img1)).unwrap()),
            vec![format!("images/{img}: missing")],
        ),
        (
            "image-not-in-colmap",
            vec!["images"],
            Box::new(move |d: &Path| {
                std::fs::rename(d.join("images").join(&img2), d.join("images/renamed.png")).unwrap()
            }),
            vec![
                "images/renamed.png: not in the COLMAP model".into(),
                format!("images/{img_b}: missing"),
            ],
        ),
        (
            "truncated-ply",
            vec!["point_cloud.ply"],
            Box::new(|d: &Path| {
                let p = d.join("point_cloud.ply");
                let len = std::fs::metadata(&p).unwrap().len();
                let f = std::fs::OpenOptions::new().write(true).open(&p).unwrap();
                f.set_len(len / 2).unwrap();
            }),
            vec!["point_cloud.ply: ".into()],
        ),
        (
            "nan-position",
            vec!["point_cloud.ply"],
            Box::new(move |d: &Path| {
                set_property(&d.join("point_cloud.ply"), n / 3, "y", f32::NAN)
            }),
            vec![format!(
                "point_cloud.ply: 1 of {n} Gaussians have a non-finite position"
            )],
        ),
        (
            // Every Gaussian invalid (a log-scale far beyond exp's range): nothing to draw.
            "no-drawable-gaussian",
            vec!["point_cloud.ply"],
            Box::new(move |d: &Path| {
                let p = d.join("point_cloud.ply");
                let mut b = std::fs::read(&p).unwrap();
                let (start, stride, off) = ply_layout(&b, "scale_0");
                for v in 0..n {
                    let o = start + v * stride + off;
                    b[o..o + 4].copy_from_slice(&1e30f32.to_le_bytes());
                }
                std::fs::write(&p, b).unwrap();
            }),
            vec![format!(
                "point_cloud.ply: none of the {n} Gaussians can be drawn"
            )],
        ),
        (
            // A SAM list cut short (a partial copy): found by the check, not by the masks
            // stage after the raycast and the render.
            "truncated-masks",
            vec!["masks"],
            Box::new(move |d: &Path| {
                let p = d.join(format!("masks/{stem1}.json"));
                let b = std::fs::read(&p).unwrap();
                std::fs::write(&p, &b[..b.len() / 2]).unwrap();
            }),
            vec![format!("masks/{stem}.json: not a JSON list of SAM masks")],
        ),
        (
            "zero-feature-row",
            vec!["features"],
            Box::new(move |d: &Path| {
                let p = d.join(format!("features/{stem2}.npy"));
                let (n, dim, mut data) = gs4city::sam::read_features(&p, None).unwrap();
                assert!(n > 1);
                data[dim..2 * dim].fill(0.0);
                let rows: Vec<Vec<f32>> = data.chunks(dim).map(<[f32]>::to_vec).collect();
                gs4city::sam::write_features_npy(&p, dim, &rows).unwrap();
            }),
            vec![format!(
                "features/{}.npy: row 1 is all zero",
                views[2].stem()
            )],
        ),
        (
            // A mistyped exponent: the vertex lands far outside the scene frame, which the
            // citymodel stage refuses; the check says so first.
            "coordinate-beyond-the-frame",
            vec!["citymodel"],
            Box::new(move |d: &Path| {
                let p = d.join("citymodel").join(&gml1);
                let text = std::fs::read_to_string(&p).unwrap();
                let at = text.find("<gml:posList").unwrap();
                let open = at + text[at..].find('>').unwrap() + 1;
                let first_end = open + text[open..].find(' ').unwrap();
                let changed = format!("{}1e300{}", &text[..open], &text[first_end..]);
                std::fs::write(&p, changed).unwrap();
            }),
            vec![format!("citymodel/{gml_name}: line ")],
        ),
        (
            // A rig's layout: one file name in two camera folders.
            "rig-stem-clash",
            vec!["sparse", "images"],
            Box::new(move |d: &Path| {
                let sparse = d.join("sparse/0");
                let mut vs = gs4city::colmap::read_model(&sparse).unwrap();
                for (k, cam) in ["camA", "camB"].into_iter().enumerate() {
                    let new = format!("{cam}/x.png");
                    std::fs::create_dir_all(d.join("images").join(cam)).unwrap();
                    std::fs::rename(
                        d.join("images").join(&vs[k].name),
                        d.join("images").join(&new),
                    )
                    .unwrap();
                    vs[k].name = new;
                }
                std::fs::remove_dir_all(&sparse).unwrap();
                gs4city::colmap::write_model(&sparse, &vs, true).unwrap();
            }),
            vec!["sparse/0: image camB/x.png: shares the file stem `x` with camA/x.png".into()],
        ),
        (
            "shifted-50m",
            vec!["citymodel"],
            Box::new(move |d: &Path| {
                write_alignment(d, &|a| {
                    let t = a["translation"][0].as_f64().unwrap();
                    a["translation"][0] = serde_json::json!(t + 50.0 * scale);
                })
            }),
            vec!["citymodel/alignment.json: alignment looks off by ~".into()],
        ),
        (
            "rotated-90",
            vec!["citymodel"],
            Box::new(move |d: &Path| {
                write_alignment(d, &|a| {
                    // R' = Rz(90°)·R: the city model turned a quarter about the up axis.
                    let r = a["rotation"].clone();
                    let row = |i: usize| -> Vec<f64> {
                        (0..3).map(|j| r[i][j].as_f64().unwrap()).collect()
                    };
                    let (r0, r1, r2) = (row(0), row(1), row(2));
                    let neg: Vec<f64> = r1.iter().map(|x| -x).collect();
                    a["rotation"] = serde_json::json!([neg, r0, r2]);
                })
            }),
            vec!["citymodel/alignment.json: alignment looks off by ~".into()],
        ),
    ];
    for (name, copied, change, want) in &cases {
        let d = r.join(name);
        variant(&base, &d, copied);
        change(&d);
        let (ok, _, err) = cli_in(None, &["check", "--scene", s(&d)]);
        assert!(!ok, "{name}: check must fail");
        let lines = error_lines(&err);
        assert_eq!(lines.len(), want.len(), "{name}: {err}");
        for w in want {
            assert!(
                lines.iter().any(|l| l.contains(w.as_str())),
                "{name}: no error line with {w:?}: {err}"
            );
        }
        // The run stops at the same check, before any stage folder exists.
        let out = r.join(format!("{name}.run"));
        let (ok, _, err) = cli_in(None, &["-q", "run", "--scene", s(&d), "--out", s(&out)]);
        assert!(!ok, "{name}: run must fail");
        assert!(err.contains(want[0].as_str()), "{name}: {err}");
        assert!(
            !out.join("citymodel").exists() && !out.join("run.json").exists(),
            "{name}: a stage ran"
        );
    }

    // Before `run --refine-alignment` the same alignment is a warning: the refinement runs next.
    let report = gs4city::inspect::check(
        &r.join("shifted-50m"),
        &gs4city::inspect::CheckOptions {
            refine_next: true,
            ..Default::default()
        },
    );
    assert_eq!(report.of(gs4city::inspect::Severity::Error).count(), 0);
    assert!(
        report
            .of(gs4city::inspect::Severity::Warning)
            .any(|f| f.to_string().contains("alignment looks off by ~")),
        "the shifted alignment must still be reported"
    );

    // A duplicate gml:id: a warning naming the id, exit 0.
    let d = r.join("duplicate-id");
    variant(&base, &d, &["citymodel"]);
    let gml = std::fs::read_dir(d.join("citymodel"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "gml"))
        .min()
        .unwrap();
    let text = std::fs::read_to_string(&gml).unwrap();
    let ids: Vec<&str> = text
        .match_indices("gml:id=\"")
        .map(|(i, m)| {
            let rest = &text[i + m.len()..];
            &rest[..rest.find('"').unwrap()]
        })
        .collect();
    let (first, second) = (ids[0], ids[ids.len() / 2]);
    assert_ne!(first, second);
    let changed = text.replacen(
        &format!("gml:id=\"{second}\""),
        &format!("gml:id=\"{first}\""),
        1,
    );
    std::fs::write(&gml, changed).unwrap();
    let (ok, out, err) = cli_in(None, &["check", "--scene", s(&d)]);
    assert!(ok, "a duplicate gml:id is a warning: {err}");
    assert!(
        err.lines()
            .any(|l| l.starts_with("warning: ") && l.contains(&format!("gml:id {first}"))),
        "{err}"
    );
    assert!(out.contains(" 0 errors"), "{out}");

    // A PNG cut short after its header (a partial copy): the run needs no pixels, so a
    // warning naming the image, exit 0; the intact images are not named.
    let d = r.join("truncated-image");
    variant(&base, &d, &["images"]);
    let p = d.join("images").join(img);
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let (ok, _, err) = cli_in(None, &["check", "--scene", s(&d)]);
    assert!(ok, "a truncated image is a warning: {err}");
    let warned: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("warning: ") && l.contains("truncated"))
        .collect();
    assert_eq!(warned.len(), 1, "{err}");
    assert!(warned[0].contains(&format!("images/{img}")), "{err}");
    let _ = std::fs::remove_dir_all(&r);
}

#[test]
fn a_3dgs_training_output_becomes_a_scene_that_runs_resumes_and_queries_from_anywhere() {
    let r = root("import");
    let sim = r.join("sim");
    synth(&sim);
    // The INRIA layout: the COLMAP folder 3DGS was trained from, and its training output.
    let data = r.join("data");
    copy_tree(&sim.join("sparse"), &data.join("sparse"));
    copy_tree(&sim.join("images"), &data.join("images"));
    let output = r.join("output");
    let it = |n: u32| output.join(format!("point_cloud/iteration_{n}"));
    std::fs::create_dir_all(it(7000)).unwrap();
    std::fs::create_dir_all(it(30000)).unwrap();
    std::fs::write(it(7000).join("point_cloud.ply"), b"ply\nformat ascii 1.0\n").unwrap();
    std::fs::copy(
        sim.join("point_cloud.ply"),
        it(30000).join("point_cloud.ply"),
    )
    .unwrap();
    std::fs::write(output.join("cameras.json"), "[]").unwrap();
    std::fs::write(
        output.join("cfg_args"),
        format!(
            "Namespace(sh_degree=3, source_path='{}', model_path='{}', images='images', resolution=-1, white_background=False, data_device='cuda', eval=False)",
            data.display(),
            output.display()
        ),
    )
    .unwrap();
    let gml = r.join("lod3");
    std::fs::create_dir_all(&gml).unwrap();
    for e in std::fs::read_dir(sim.join("citymodel")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "gml") {
            std::fs::copy(&p, gml.join(p.file_name().unwrap())).unwrap();
        }
    }
    std::fs::copy(
        sim.join("citymodel/alignment.json"),
        r.join("alignment.json"),
    )
    .unwrap();
    let _ = std::fs::remove_dir_all(&sim);

    // The guide's commands, run from `r`.
    let (ok, out, err) = cli_in(
        Some(&r),
        &[
            "scene",
            "import",
            "--model",
            "output",
            "--citygml",
            "lod3",
            "--alignment",
            "alignment.json",
            "--out",
            "S",
        ],
    );
    assert!(ok, "{err}");
    assert!(out.contains("ready"), "{out}\n{err}");
    let scene = r.join("S");
    assert_eq!(
        std::fs::canonicalize(scene.join("point_cloud.ply")).unwrap(),
        std::fs::canonicalize(it(30000).join("point_cloud.ply")).unwrap(),
        "the highest iteration"
    );
    assert!(
        scene.join("sparse/0/images.bin").is_file() || scene.join("sparse/0/images.txt").is_file()
    );
    let (ok, _, err) = cli_in(Some(&r), &["-q", "run", "--scene", "S", "--out", "R"]);
    assert!(ok, "{err}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(r.join("R/summary.json")).unwrap()).unwrap();
    // The split does not depend on gt/ (absent here): every 8th image by name is a test view.
    let mut names: Vec<String> = std::fs::read_dir(scene.join("images"))
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            p.file_stem().unwrap().to_string_lossy().into_owned()
        })
        .collect();
    names.sort();
    let expected: Vec<String> = names.iter().step_by(8).cloned().collect();
    let got: Vec<String> = summary["test_views"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    assert!(!expected.is_empty());
    assert_eq!(got, expected);
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(r.join("R/run.json")).unwrap()).unwrap();
    let recorded = PathBuf::from(record["scene"].as_str().unwrap());
    assert_eq!(recorded, std::fs::canonicalize(&scene).unwrap());

    // Resumed, however the scene is spelled.
    let abs = std::fs::canonicalize(&scene).unwrap();
    for spelling in ["S", "./S/", abs.to_str().unwrap()] {
        let (ok, out, err) = cli_in(Some(&r), &["-q", "run", "--scene", spelling, "--out", "R"]);
        assert!(ok, "{spelling}: {err}");
        let rows: Vec<&str> = out
            .lines()
            .skip(1)
            .take_while(|l| !l.trim().is_empty() && !l.starts_with("report:"))
            .collect();
        assert!(rows.len() >= 7, "{out}");
        assert!(
            rows.iter().all(|l| l.ends_with("(resumed)")),
            "--scene {spelling} reran a stage:\n{out}"
        );
    }

    // A query from `/`, with the run given absolutely.
    let run = std::fs::canonicalize(r.join("R")).unwrap();
    let q = r.join("Q");
    let (ok, out, err) = cli_in(
        Some(Path::new("/")),
        &[
            "-q",
            "query",
            "--run",
            s(&run),
            "--class",
            "Window",
            "--views",
            "all",
            "--out",
            s(&q),
        ],
    );
    assert!(ok, "{err}");
    assert!(out.contains("view masks"), "{out}");
    assert!(std::fs::read_dir(&q).unwrap().any(|e| {
        e.unwrap()
            .file_name()
            .to_string_lossy()
            .ends_with(".mask.npy")
    }));
    let _ = std::fs::remove_dir_all(&r);
}

#[test]
fn invalid_gaussians_stay_in_semantic_ply_and_class_query_masks_equal_the_class_maps() {
    let r = root("semantic");
    let base = r.join("base");
    synth(&base);
    let scene = r.join("S");
    variant(&base, &scene, &["point_cloud.ply"]);
    let ply = scene.join("point_cloud.ply");
    let bad = 1234;
    set_property(&ply, bad, "scale_0", 100.0); // out of the log-scale range: invalid
    let (ok, _, err) = cli_in(None, &["check", "--scene", s(&scene)]);
    assert!(ok, "an invalid Gaussian is a warning: {err}");
    assert!(
        err.lines().any(|l| l.starts_with("warning: ")
            && l.contains("point_cloud.ply: 1 of ")
            && l.contains(&format!("vertex {bad}"))),
        "{err}"
    );
    let run = r.join("R");
    let (ok, _, err) = cli_in(None, &["-q", "run", "--scene", s(&scene), "--out", s(&run)]);
    assert!(ok, "{err}");
    let input = gs4city::splat::read_ply(&ply, &gs4city::splat::ReadOptions::KEEP)
        .unwrap()
        .0;
    let (out, _) = gs4city::splat::read_ply(
        &run.join("lift/semantic.ply"),
        &gs4city::splat::ReadOptions::KEEP,
    )
    .unwrap();
    assert_eq!(out.len(), input.len(), "every input Gaussian");
    assert_eq!(out.positions, input.positions, "in input order");
    let label = &out.extra("label").unwrap().values;
    assert_eq!(label[bad], -1.0);
    assert!(label.iter().filter(|&&l| l >= 0.0).count() > input.len() / 4);
    let lift: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("lift/summary.json")).unwrap())
            .unwrap();
    assert_eq!(lift["invalid"], 1);

    // The class query's masks are the class maps' Window pixels (test views).
    let q = r.join("Q");
    let (ok, _, err) = cli_in(
        None,
        &[
            "-q",
            "query",
            "--run",
            s(&run),
            "--class",
            "Window",
            "--out",
            s(&q),
        ],
    );
    assert!(ok, "{err}");
    let mut compared = 0;
    for e in std::fs::read_dir(run.join("lift")).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(".class.npy") else {
            continue;
        };
        let (_, class) = gs4city::npy::read::<i32>(&run.join("lift").join(&name)).unwrap();
        let (_, mask) = gs4city::npy::read::<u8>(&q.join(format!("{stem}.mask.npy"))).unwrap();
        let want: Vec<u8> = class
            .iter()
            .map(|&c| u8::from(c == gs4city::classes::WINDOW))
            .collect();
        assert!(want.contains(&1), "{stem} shows windows");
        assert_eq!(mask, want, "{stem}");
        compared += 1;
    }
    assert!(compared >= 1);
    let _ = std::fs::remove_dir_all(&r);
}

/// `scene import` that cannot find the COLMAP folder says why (the training output's
/// `cfg_args` has no readable `source_path`) and exits with an error, though the folder is
/// written for the user to complete.
#[test]
fn an_import_with_problems_names_them_and_fails() {
    let r = root("import-fails");
    let model = r.join("output");
    let it = model.join("point_cloud/iteration_10");
    std::fs::create_dir_all(&it).unwrap();
    std::fs::write(it.join("point_cloud.ply"), b"ply\nformat ascii 1.0\n").unwrap();
    std::fs::write(model.join("cfg_args"), "not a namespace at all").unwrap();
    let gml = r.join("lod3");
    std::fs::create_dir_all(&gml).unwrap();
    let import = |cwd: Option<&Path>, out: &Path| {
        cli_in(
            cwd,
            &[
                "scene",
                "import",
                "--model",
                s(&model),
                "--citygml",
                s(&gml),
                "--out",
                s(out),
            ],
        )
    };
    let out = r.join("S");
    let (ok, stdout, err) = import(None, &out);
    assert!(!ok, "{stdout}\n{err}");
    let cfg = model.join("cfg_args");
    assert!(
        stdout.contains(&format!(
            "not found: sparse/0 ({} holds no readable source_path",
            cfg.display()
        )),
        "{stdout}"
    );
    assert!(
        err.contains("problems must be fixed before `gs4city run`"),
        "{err}"
    );
    assert!(out.join("point_cloud.ply").exists());
    // A relative source_path (as train.py records it when given one) is found beside the
    // training output, wherever the import runs from.
    let data = r.join("data");
    std::fs::create_dir_all(data.join("sparse/0")).unwrap();
    std::fs::create_dir_all(data.join("images")).unwrap();
    std::fs::write(data.join("sparse/0/images.txt"), "").unwrap();
    std::fs::write(
        model.join("cfg_args"),
        "Namespace(source_path='data', images='images')",
    )
    .unwrap();
    let (_, stdout, _) = import(Some(Path::new("/")), &r.join("S2"));
    assert!(
        stdout
            .lines()
            .any(|l| l.starts_with("sparse/0") && l.contains("data/sparse/0")),
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&r);
}

/// `--test-every 0` on a scene with ground truth: every view trains, the run finishes and eval
/// is skipped (with a warning), instead of refusing to start.
#[test]
fn every_view_can_train_on_a_scene_with_ground_truth() {
    let r = root("test-every-0");
    let scene = r.join("S");
    synth(&scene);
    let out = r.join("R");
    let (ok, _, err) = cli_in(
        None,
        &[
            "-q",
            "run",
            "--scene",
            s(&scene),
            "--out",
            s(&out),
            "--test-every",
            "0",
        ],
    );
    assert!(ok, "{err}");
    assert!(err.contains("eval is skipped"), "{err}");
    assert!(out.join("report.html").is_file() && out.join("lift").is_dir());
    assert!(!out.join("eval").exists());
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["test_views"].as_array().map(Vec::len), Some(0));
    let _ = std::fs::remove_dir_all(&r);
}

/// A polygon of 12,000 points (all on one circle: the triangulation's slowest case) is named
/// in a warning by the check, which stays fast, and skipped by the citymodel stage, which
/// names it too and still triangulates every other polygon.
#[test]
fn a_polygon_over_the_point_limit_is_named_and_skipped_not_triangulated() {
    let r = root("longring");
    let base = r.join("base");
    synth(&base);
    let d = r.join("long");
    variant(&base, &d, &["citymodel"]);
    let align: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(base.join("citymodel/alignment.json")).unwrap(),
    )
    .unwrap();
    let o: Vec<f64> = (0..3)
        .map(|k| align["origin"][k].as_f64().unwrap())
        .collect();
    let n = 12_000;
    let ring: Vec<[f64; 3]> = (0..=n)
        .map(|i| {
            let t = std::f64::consts::TAU * (i % n) as f64 / n as f64;
            [o[0] + 5.0 * t.cos(), o[1], o[2] + 5.0 + 5.0 * t.sin()]
        })
        .collect();
    std::fs::write(
        d.join("citymodel/zz_long.gml"),
        crate::common::one_wall_citygml("ROUND", "LONG_RING", &ring),
    )
    .unwrap();
    let (ok, _, err) = cli_in(None, &["check", "--scene", s(&d)]);
    assert!(ok, "{err}");
    let warned: Vec<&str> = err.lines().filter(|l| l.contains("LONG_RING")).collect();
    assert_eq!(warned.len(), 1, "{err}");
    assert!(
        warned[0].contains("zz_long.gml") && warned[0].contains("more than the 10000"),
        "{err}"
    );
    let out = r.join("cm");
    let (ok, _, err) = cli_in(
        None,
        &["citymodel", s(&d.join("citymodel")), "--out", s(&out)],
    );
    assert!(ok, "{err}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let skipped: Vec<&serde_json::Value> = summary["skipped"]["polygons"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["polygon"] == "LONG_RING")
        .collect();
    assert_eq!(skipped.len(), 1, "{summary}");
    assert!(
        skipped[0]["reason"]
            .as_str()
            .unwrap()
            .contains("12000 points, more than the 10000"),
        "{summary}"
    );
    let mesh = gs4city::mesh::TriMesh::read_ply(&out.join("mesh.ply")).unwrap();
    assert!(!mesh.faces.is_empty());
}
