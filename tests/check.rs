//! End to end on SIMULATED scenes (`synth --preset small`): `gs4city check` names each defect
//! of a scene in one line and `run` stops before any stage; README.md's own-capture guide runs as
//! written (a 3DGS training output becomes a scene folder, clicked ground-control points give
//! its alignment, it runs, resumes however `--scene` is spelled, and `query --run R` works from
//! `/`); invalid Gaussians stay in `semantic.ply` labelled −1; a class query's view masks are the
//! class maps' pixels of that class.
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

    // The verdict's advice is what works: beyond the refinement's reach (50 m) it asks for new
    // ground-control points, and `align --refine` indeed refuses; within it (2 m diagonally,
    // judged implausible with `[check] max_offset = 0.5`) it advises the refinement, which
    // recovers the alignment.
    let refine = |d: &Path| {
        let out = d.join("refined/alignment.json");
        std::fs::create_dir_all(out.parent().unwrap()).unwrap();
        let (ok, _, err) = cli_in(
            None,
            &[
                "align",
                "--refine",
                "--citymodel",
                s(&d.join("citymodel")),
                "--ply",
                s(&d.join("point_cloud.ply")),
                "--colmap",
                s(&d.join("sparse/0")),
                "--out",
                s(&out),
            ],
        );
        (ok, err, out)
    };
    let far = r.join("shifted-50m");
    let (_, _, err) = cli_in(None, &["check", "--scene", s(&far)]);
    assert!(
        err.contains("beyond the reach of `gs4city align --refine`")
            && err.contains("gs4city align --points"),
        "{err}"
    );
    let (ok, err, _) = refine(&far);
    assert!(
        !ok,
        "refine recovered what check called beyond its reach: {err}"
    );
    let near = r.join("shifted-2m");
    variant(&base, &near, &["citymodel"]);
    write_alignment(&near, &|a| {
        for k in 0..3 {
            let t = a["translation"][k].as_f64().unwrap();
            a["translation"][k] = serde_json::json!(t + 2.0 * scale / 3f64.sqrt());
        }
    });
    let strict = r.join("strict.toml");
    std::fs::write(&strict, "[check]\nmax_offset = 0.5\n").unwrap();
    let (ok, _, err) = cli_in(
        None,
        &["check", "--scene", s(&near), "--config", s(&strict)],
    );
    assert!(!ok, "{err}");
    assert!(
        err.contains("within the reach of `gs4city align --refine`")
            && err.contains("--refine-alignment"),
        "{err}"
    );
    let (ok, err, out) = refine(&near);
    assert!(ok, "check advised a refinement that refuses: {err}");
    let got = gs4city::alignment::Alignment::read(&out).unwrap();
    let want = gs4city::alignment::Alignment::read(&base.join("citymodel/alignment.json")).unwrap();
    let p = want.origin + glam::DVec3::new(10.0, 10.0, 5.0);
    let off = (got.apply(p) - want.apply(p)).length() / scale;
    assert!(off < 0.01, "refined {off} m from the truth");

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

/// The commands of README.md's section "Run it on your own capture", in order: the lines of
/// its ```sh blocks that start with `gs4city`.
fn readme_capture_commands() -> Vec<Vec<String>> {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let start = readme
        .find("## Run it on your own capture")
        .expect("README has the capture guide");
    let section = &readme[start..];
    let section = &section[..section[3..].find("\n## ").map_or(section.len(), |e| e + 3)];
    let mut cmds = Vec::new();
    let mut in_sh = false;
    for line in section.lines() {
        match line.trim() {
            "```sh" => in_sh = true,
            "```" => in_sh = false,
            l if in_sh && l.starts_with("gs4city ") => {
                let l = l.split(" #").next().unwrap();
                cmds.push(l.split_whitespace().skip(1).map(String::from).collect());
            }
            _ => {}
        }
    }
    cmds
}

/// `GET target` from 127.0.0.1:`port` (one request, `Connection: close`): status and JSON body.
fn http_json(port: u16, target: &str) -> (u16, serde_json::Value) {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    c.set_read_timeout(Some(std::time::Duration::from_secs(120)))
        .unwrap();
    write!(
        c,
        "GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut resp = Vec::new();
    c.read_to_end(&mut resp).unwrap();
    let text = String::from_utf8_lossy(&resp).into_owned();
    let status = text[9..12].parse().unwrap();
    let body = &text[text.find("\r\n\r\n").unwrap() + 4..];
    (
        status,
        serde_json::from_str(body).unwrap_or_else(|e| panic!("{target}: {e}: {body}")),
    )
}

/// A `gs4city view …` server started in `cwd`, stopped on drop.
struct Viewer {
    child: std::process::Child,
    port: u16,
}

impl Viewer {
    fn start(cwd: &Path, args: &[String]) -> Viewer {
        use std::io::BufRead;
        let mut child = Command::new(env!("CARGO_BIN_EXE_gs4city"))
            .current_dir(cwd)
            .args(args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let port = line
            .split_whitespace()
            .find_map(|w| w.strip_prefix("http://127.0.0.1:"))
            .and_then(|w| w.trim_end_matches('/').parse().ok())
            .unwrap_or_else(|| panic!("no URL in `{line}`"));
        Viewer { child, port }
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A point on a building's wall near one of its corners (the simulator's truth), and a camera
/// that sees it: the test's knowledge of where corners appear.
struct Corner {
    geo: glam::DVec3,
    scene: glam::DVec3,
    eye: glam::DVec3,
}

/// Up to `n` wall points near corners, spread over the buildings, their walls and heights, with
/// an eye `dist` metres in front of each (outside its building), from the true alignment.
fn corners(gml: &[PathBuf], truth: &gs4city::alignment::Alignment, n: usize) -> Vec<Corner> {
    use glam::DVec3;
    let out = gs4city::citymodel::run(
        gml,
        &gs4city::citymodel::Options {
            alignment: Some(*truth),
        },
    )
    .unwrap();
    let m = &out.mesh;
    let v = |i: u32| DVec3::from(m.vertices[i as usize].map(f64::from));
    // Building centres (scene frame).
    let mut centre: std::collections::BTreeMap<i32, (DVec3, f64)> = Default::default();
    for (f, l) in m.faces.iter().zip(&m.labels) {
        let e = centre.entry(l.feature).or_insert((DVec3::ZERO, 0.0));
        e.0 += v(f[0]);
        e.1 += 1.0;
    }
    let up = truth.rotation * DVec3::Z;
    let mut cands: Vec<(i32, f64, Corner)> = Vec::new();
    for (f, l) in m.faces.iter().zip(&m.labels) {
        let wall = l.part < 0
            && l.surface >= 0
            && out.entities[l.surface as usize].class == gs4city::semantics::Class::WallSurface;
        let (a, b, c) = (v(f[0]), v(f[1]), v(f[2]));
        let cross = (b - a).cross(c - a);
        let area = 0.5 * cross.length() / (truth.scale * truth.scale);
        if !wall || area < 6.0 || cross.normalize().dot(up).abs() > 0.2 {
            continue;
        }
        let (sum, k) = centre[&l.feature];
        let mut nrm = cross.normalize();
        if nrm.dot(a - sum / k) < 0.0 {
            nrm = -nrm;
        }
        // 0.6 m into the triangle from its vertex: on the wall, beside the corner.
        let g = (a + b + c) / 3.0;
        let p = a + (g - a).normalize() * (0.6 * truth.scale).min((g - a).length() * 0.5);
        let eye = p + nrm * (5.0 * truth.scale) + up * (0.5 * truth.scale);
        let h = p.dot(up);
        cands.push((
            l.feature,
            h,
            Corner {
                geo: truth.unapply(p),
                scene: p,
                eye,
            },
        ));
    }
    // Round robin over the buildings, alternating low and high points.
    cands.sort_by(|x, y| x.0.cmp(&y.0).then(x.1.total_cmp(&y.1)));
    let mut by_building: std::collections::BTreeMap<i32, Vec<Corner>> = Default::default();
    for (b, _, c) in cands {
        by_building.entry(b).or_default().push(c);
    }
    let mut lists: Vec<std::collections::VecDeque<Corner>> = by_building
        .into_values()
        .map(|mut l| {
            // Low and high alternately.
            let mut out = std::collections::VecDeque::new();
            let mut hi = true;
            while !l.is_empty() {
                let c = if hi { l.pop() } else { Some(l.remove(0)) };
                out.extend(c);
                hi = !hi;
            }
            out
        })
        .collect();
    let mut picked = Vec::new();
    while picked.len() < n && lists.iter().any(|l| !l.is_empty()) {
        for l in &mut lists {
            if let Some(c) = l.pop_front() {
                picked.push(c);
            }
        }
    }
    picked.truncate(n);
    picked
}

/// The own-capture route of README.md, run as written: its commands (the ```sh lines of
/// "Run it on your own capture") in a folder laid out as the guide says — a SIMULATED capture
/// (`synth --preset small`) as an INRIA training output (`output/point_cloud/iteration_N/`,
/// `cfg_args`), its COLMAP folder and the CityGML folder, **without an alignment**. The one change
/// to a command: the viewer gets a free port (`--port 0`; the test runs beside others). Between
/// them the test does what the guide asks of its reader: it clicks building corners through the
/// viewer's HTTP API (`/api/point`, the page's own request) from cameras it places with the
/// simulator's true alignment (test-side knowledge, used nowhere else), and writes `pairs.csv`
/// from the corners' CityGML coordinates and the clicked scene coordinates. Every step succeeds;
/// the clicks land within 5 cm of the truth, the estimated alignment within 5 cm; a second import
/// into the same folder is accepted, an import into a foreign folder refused with the hint; the
/// run trains on every view; `run` resumes however the scene is spelled and `query --run R` works
/// from `/`; `query --pick` and the viewer after the run give the point in the city model's CRS.
#[test]
fn the_readme_capture_guide_runs_as_written() {
    use glam::DVec3;
    let r = root("guide");
    let sim = r.join("sim");
    synth(&sim);
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sim.join("summary.json")).unwrap()).unwrap();
    let truth = gs4city::alignment::Alignment::from_json_str(
        Path::new("alignment_true"),
        &summary["alignment_true"].to_string(),
    )
    .unwrap();
    // The INRIA layout: the COLMAP folder 3DGS was trained from, its training output, the model.
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
        "Namespace(sh_degree=3, source_path='data', model_path='output', images='images', resolution=-1, white_background=False, data_device='cuda', eval=False)",
    )
    .unwrap();
    let gml = r.join("lod3");
    std::fs::create_dir_all(&gml).unwrap();
    let mut gml_files = Vec::new();
    for e in std::fs::read_dir(sim.join("citymodel")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "gml") {
            let dst = gml.join(p.file_name().unwrap());
            std::fs::copy(&p, &dst).unwrap();
            gml_files.push(dst);
        }
    }
    gml_files.sort();
    let _ = std::fs::remove_dir_all(&sim); // nothing of the simulation is left beside the capture

    let cmds = readme_capture_commands();
    let kinds: Vec<String> = cmds.iter().map(|c| c[..2].join(" ")).collect();
    assert_eq!(
        kinds,
        [
            "scene import",
            "view --scene",
            "align --points",
            "check --scene",
            "run --scene",
            "query --run"
        ],
        "the guide's commands: {cmds:?}"
    );
    let run_cmd = |c: &Vec<String>| {
        let args: Vec<&str> = c.iter().map(String::as_str).collect();
        let (ok, out, err) = cli_in(Some(&r), &args);
        assert!(ok, "`gs4city {}` failed:\n{out}\n{err}", c.join(" "));
        (out, err)
    };

    // 1. The scene folder, before any alignment exists.
    let (out, _) = run_cmd(&cmds[0]);
    assert!(out.contains("next, its alignment"), "{out}");
    let scene = r.join("S");
    assert_eq!(
        std::fs::canonicalize(scene.join("point_cloud.ply")).unwrap(),
        std::fs::canonicalize(it(30000).join("point_cloud.ply")).unwrap(),
        "the highest iteration"
    );
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("scene.json")).unwrap()).unwrap();
    assert!(
        meta.get("test_views").is_none() && meta["simulated"] == false,
        "{meta}"
    );
    // Imported again into the same folder: accepted; into a folder of other files: refused with
    // the way out.
    run_cmd(&cmds[0]);
    let foreign = r.join("F");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), "mine").unwrap();
    let mut other = cmds[0].clone();
    *other.last_mut().unwrap() = "F".into();
    let args: Vec<&str> = other.iter().map(String::as_str).collect();
    let (ok, _, err) = cli_in(Some(&r), &args);
    assert!(!ok && err.contains("--force"), "{err}");
    assert_eq!(
        std::fs::read_to_string(foreign.join("notes.txt")).unwrap(),
        "mine"
    );

    // 2. Ground-control points: the viewer opens the scene before any run; clicks on corners.
    let mut view = cmds[1].clone();
    view.extend(["--port".into(), "0".into()]);
    let srv = Viewer::start(&r, &view);
    let (st, meta) = http_json(srv.port, "/api/meta");
    assert_eq!(st, 200);
    assert!(
        meta["run"].is_null() && meta["georeferenced"] == false,
        "{meta}"
    );
    let up = truth.rotation * DVec3::Z;
    let mut pairs = String::from("# geo_x geo_y geo_z scene_x scene_y scene_z\n");
    let (mut clicked, mut errors) = (0, Vec::new());
    for c in corners(&gml_files, &truth, 10) {
        let csv = |v: DVec3| format!("{},{},{}", v.x, v.y, v.z);
        let (w, h) = (640.0, 480.0);
        let (st, j) = http_json(
            srv.port,
            &format!(
                "/api/point?eye={}&target={}&up={}&fovy=50&width={w}&height={h}&x={}&y={}",
                csv(c.eye),
                csv(c.scene),
                csv(up),
                w / 2.0,
                h / 2.0
            ),
        );
        assert_eq!(st, 200, "{j}");
        if j["hit"] != true {
            continue;
        }
        let p: Vec<f64> = (0..3).map(|k| j["scene"][k].as_f64().unwrap()).collect();
        let p = DVec3::new(p[0], p[1], p[2]);
        let err_m = (p - c.scene).length() / truth.scale;
        errors.push(err_m);
        // A corner hidden behind a tree is a misclick a user would not keep.
        if err_m < 0.05 {
            pairs.push_str(&format!(
                "{:.4} {:.4} {:.4}   {:.6} {:.6} {:.6}\n",
                c.geo.x, c.geo.y, c.geo.z, p.x, p.y, p.z
            ));
            clicked += 1;
        }
    }
    assert!(
        clicked >= 6,
        "{clicked} of the clicks on corners within 5 cm: {errors:?}"
    );
    drop(srv);
    std::fs::write(r.join("pairs.csv"), &pairs).unwrap();

    // 3. The alignment from the pairs, within 5 cm of the truth over the model; the check.
    run_cmd(&cmds[2]);
    let est = gs4city::alignment::Alignment::read(&scene.join("citymodel/alignment.json")).unwrap();
    let worst = corners(&gml_files, &truth, 40)
        .iter()
        .map(|c| (est.apply(c.geo) - c.scene).length() / truth.scale)
        .fold(0.0f64, f64::max);
    assert!(worst < 0.05, "the estimated alignment is {worst} m off");
    run_cmd(&cmds[3]);

    // 4. Run and query, as written: every view trains.
    let (_, _) = run_cmd(&cmds[4]);
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(r.join("R/summary.json")).unwrap()).unwrap();
    assert_eq!(summary["test_views"].as_array().map(Vec::len), Some(0));
    let (out, _) = run_cmd(&cmds[5]);
    assert!(out.contains("view masks"), "{out}");
    let n_views = std::fs::read_dir(scene.join("images")).unwrap().count();
    let masks = std::fs::read_dir(r.join("Q"))
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .ends_with(".mask.npy")
        })
        .count();
    assert_eq!(masks, n_views, "--views all");
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(r.join("R/run.json")).unwrap()).unwrap();
    assert_eq!(
        PathBuf::from(record["scene"].as_str().unwrap()),
        std::fs::canonicalize(&scene).unwrap()
    );
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

    // After the run: the viewer's click and `query --pick` give the point in the model's CRS.
    let run = std::fs::canonicalize(r.join("R")).unwrap();
    let srv = Viewer::start(
        Path::new("/"),
        &["view", "--run", s(&run), "--port", "0"].map(String::from),
    );
    let c = &corners(&gml_files, &truth, 1)[0];
    let csv = |v: DVec3| format!("{},{},{}", v.x, v.y, v.z);
    let (st, j) = http_json(
        srv.port,
        &format!(
            "/api/point?eye={}&target={}&up={}&fovy=50&width=640&height=480&x=320&y=240",
            csv(c.eye),
            csv(c.scene),
            csv(up)
        ),
    );
    assert_eq!(st, 200, "{j}");
    let g: Vec<f64> = (0..3).map(|k| j["geo"][k].as_f64().unwrap()).collect();
    let off = (DVec3::new(g[0], g[1], g[2]) - c.geo).length();
    assert!(off < 0.1, "viewer's CRS point {off} m from the corner: {j}");
    drop(srv);
    // `query --pick` from `/`: a pixel of a view where that corner appears.
    let views = gs4city::colmap::read_model(&scene.join("sparse/0")).unwrap();
    let mut best: Option<f64> = None;
    for v in &views {
        let cam = &v.camera;
        let Some(uv) = cam.project(cam.pose.world_to_camera(c.scene)) else {
            continue;
        };
        let k = &cam.intrinsics;
        if uv.x < 0.0 || uv.y < 0.0 || uv.x >= f64::from(k.width) || uv.y >= f64::from(k.height) {
            continue;
        }
        let q = r.join("QP");
        let (ok, out, err) = cli_in(
            Some(Path::new("/")),
            &[
                "query",
                "--run",
                s(&run),
                "--pick",
                &v.stem(),
                &(uv.x as usize).to_string(),
                &(uv.y as usize).to_string(),
                "--views",
                "none",
                "--out",
                s(&q),
            ],
        );
        assert!(ok, "{err}");
        let line = out
            .lines()
            .find(|l| l.trim_start().starts_with("point (") && !l.contains("scene frame"))
            .unwrap_or_else(|| panic!("no CRS point in:\n{out}"));
        let xyz: Vec<f64> = line
            .split_whitespace()
            .rev()
            .take(3)
            .map(|w| w.parse().unwrap())
            .collect();
        let off = (DVec3::new(xyz[2], xyz[1], xyz[0]) - c.geo).length();
        best = Some(best.map_or(off, |b: f64| b.min(off)));
    }
    let best = best.expect("the corner appears in some view");
    assert!(
        best < 0.15,
        "query --pick's CRS point is {best} m from the corner"
    );

    // A query from `/`, with the run given absolutely.
    let q = r.join("Q2");
    let (ok, out, err) = cli_in(
        Some(Path::new("/")),
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
    assert!(out.contains("match true"), "{out}");

    // An unfinished run (its vote missing, as after a run stopped before the lift stage): the
    // commands that read it name the stage and the command that resumes it.
    std::fs::rename(run.join("lift"), r.join("lift.away")).unwrap();
    for args in [
        vec![
            "query",
            "--run",
            s(&run),
            "--class",
            "Window",
            "--out",
            s(&q),
        ],
        vec!["view", "--run", s(&run), "--port", "0"],
        vec!["export", "--run", s(&run), "--out", s(&r.join("T"))],
    ] {
        let (ok, _, err) = cli_in(Some(Path::new("/")), &args);
        assert!(!ok, "{args:?}");
        assert!(
            err.contains("has not finished: stage lift")
                && err.contains(&format!(
                    "`gs4city run --scene {} --out {}` resumes the run",
                    abs.display(),
                    run.display()
                )),
            "{args:?}: {err}"
        );
        assert_eq!(err.lines().count(), 1, "{err}");
    }
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
