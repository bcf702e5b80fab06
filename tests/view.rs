//! `gs4city view` on a finished run of a SIMULATED scene (`synth --preset small`: two real
//! buildings, simulated Gaussians): the server listens on 127.0.0.1 only (read from
//! /proc/net/tcp), refuses paths outside the run folder and survives malformed requests (raw TCP
//! sockets), its query API selects, Gaussian for Gaussian, what an independent reading of the
//! expression over `semantic.ply` (`scripts/selection_reference.py`, plyfile) selects, its pick
//! API reports the
//! hierarchy `semantic.ply` stores, and in headless Chromium (Debian's, driven by playwright-core
//! from tools/js) the splat renderer (Spark, vendored from npm) draws the window's class colour
//! where the window is, a real mouse click on a window shows that window, its wall and its
//! building, and a query typed in the box highlights as many Gaussians as that reading selects.
//! The vendored renderer is byte for byte the npm package pinned in tools/js.
//! The truth is read here from `R/lift/semantic.ply` and `R/citymodel/semantics.json`.
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpStream, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

use glam::DVec3;
use gs4city::classes;
use gs4city::splat::{self, ReadOptions};
use serde_json::Value;

fn gs(args: &[&str]) -> (bool, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_gs4city"))
        .args(args)
        .output()
        .unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// A finished run of the SIMULATED small preset (synth + run, ~10 s), shared by the tests.
fn run_dir() -> &'static Path {
    static RUN: OnceLock<PathBuf> = OnceLock::new();
    RUN.get_or_init(|| {
        // Under the tests' folder (~380 MB), which the next test run removes once this
        // process has ended.
        let root = crate::common::temp_dir().join(format!("gs4city-view-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        let (scene, run) = (root.join("scene"), root.join("run"));
        let (ok, _, err) = gs(&[
            "-q",
            "synth",
            "--preset",
            "small",
            "--out",
            scene.to_str().unwrap(),
        ]);
        assert!(ok, "synth: {err}");
        let (ok, _, err) = gs(&[
            "-q",
            "run",
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
        ]);
        assert!(ok, "run: {err}");
        run
    })
}

/// A running `gs4city view R --port 0`, stopped on drop.
struct Server {
    child: Child,
    port: u16,
    url: String,
}

impl Server {
    fn start(run: &Path) -> Server {
        Server::start_with(&["--run", run.to_str().unwrap()])
    }

    /// `gs4city view ARGS --port 0`.
    fn start_with(args: &[&str]) -> Server {
        let mut child = Command::new(env!("CARGO_BIN_EXE_gs4city"))
            .arg("view")
            .args(args)
            .args(["--port", "0"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let url = line
            .split_whitespace()
            .find(|w| w.starts_with("http://"))
            .unwrap_or_else(|| panic!("no URL in `{line}`"))
            .to_string();
        let port = url
            .trim_start_matches("http://127.0.0.1:")
            .trim_end_matches('/')
            .parse()
            .unwrap_or_else(|_| panic!("`{url}` is not http://127.0.0.1:PORT/"));
        Server { child, port, url }
    }

    /// Sends `bytes` on a fresh connection; the status code, the whole response and its body.
    fn raw(&self, bytes: &[u8]) -> (u16, String, Vec<u8>) {
        let mut s = TcpStream::connect(("127.0.0.1", self.port)).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        s.set_write_timeout(Some(Duration::from_secs(30))).unwrap();
        let _ = s.write_all(bytes);
        let mut resp = Vec::new();
        let _ = s.read_to_end(&mut resp);
        let text = String::from_utf8_lossy(&resp).into_owned();
        let status = text
            .strip_prefix("HTTP/1.1 ")
            .and_then(|t| t.get(..3))
            .and_then(|c| c.parse().ok())
            .unwrap_or_else(|| panic!("no HTTP status in {:?}", &text[..text.len().min(200)]));
        let body = match resp.windows(4).position(|w| w == b"\r\n\r\n") {
            Some(p) => resp[p + 4..].to_vec(),
            None => Vec::new(),
        };
        (status, text, body)
    }

    fn get(&self, target: &str) -> (u16, Vec<u8>) {
        let (s, _, b) = self.raw(
            format!(
                "GET {target} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n\r\n",
                self.port
            )
            .as_bytes(),
        );
        (s, b)
    }

    fn get_json(&self, target: &str) -> (u16, Value) {
        let (s, b) = self.get(target);
        (
            s,
            serde_json::from_slice(&b)
                .unwrap_or_else(|e| panic!("{target}: {e}: {}", String::from_utf8_lossy(&b))),
        )
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn enc(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-_.~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

/// `gs4city query --where q`'s Gaussian count (its summary.json), or its error line.
fn cli_count(run: &Path, q: &str) -> Result<usize, String> {
    let out = run
        .parent()
        .unwrap()
        .join(format!("q-{}", enc(q).replace('%', "_")));
    let (ok, _, err) = gs(&[
        "-q",
        "query",
        "--run",
        run.to_str().unwrap(),
        "--where",
        q,
        "--views",
        "none",
        "--no-sqlite",
        "--out",
        out.to_str().unwrap(),
    ]);
    if !ok {
        return Err(err);
    }
    let s: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    Ok(s["gaussians"].as_u64().unwrap() as usize)
}

/// What `scripts/selection_reference.py` (docs/query.md's rules over `semantic.ply` read by
/// the pip package plyfile, no gs4city code) selects for each of `queries`: per query the
/// selected Gaussians' indices. `None` (a counted skip of `test`) without plyfile.
pub(crate) fn reference_selections(
    test: &str,
    run: &Path,
    queries: &[&str],
) -> Option<Vec<Vec<usize>>> {
    if !crate::common::python_can_import(test, &["numpy", "plyfile"]) {
        return None;
    }
    let o = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/selection_reference.py"))
        .arg(run)
        .args(queries)
        .arg("--indices")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    Some(
        queries
            .iter()
            .map(|q| {
                let sel: Vec<usize> = serde_json::from_value(r[*q]["indices"].clone()).unwrap();
                assert_eq!(
                    sel.len() as u64,
                    r[*q]["gaussians"].as_u64().unwrap(),
                    "{q}"
                );
                sel
            })
            .collect(),
    )
}

/// The run's truth per Gaussian from `R/lift/semantic.ply` (class, feature, surface, part
/// columns; positions, largest σ, opacity) and the entity table of `R/citymodel/semantics.json`.
struct Truth {
    pos: Vec<DVec3>,
    sigma: Vec<f64>,
    /// Raw log scales and raw quaternions `(w, x, y, z)` of `semantic.ply`.
    log_scale: Vec<[f32; 3]>,
    rot: Vec<[f32; 4]>,
    opacity: Vec<f64>,
    class: Vec<i32>,
    feature: Vec<i32>,
    surface: Vec<i32>,
    part: Vec<i32>,
    /// (gml:id, CityGML class, level) per entity id.
    entities: Vec<(String, String, String)>,
}

fn truth(run: &Path) -> Truth {
    let (g, _) = splat::read_ply(&run.join("lift/semantic.ply"), &ReadOptions::KEEP).unwrap();
    let col = |n: &str| -> Vec<i32> {
        g.extra(n)
            .unwrap_or_else(|| panic!("semantic.ply has no `{n}`"))
            .values
            .iter()
            .map(|v| *v as i32)
            .collect()
    };
    let sem: Value = serde_json::from_str(
        &std::fs::read_to_string(run.join("citymodel/semantics.json")).unwrap(),
    )
    .unwrap();
    let entities = sem["entities"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .map(|(i, e)| {
            assert_eq!(e["id"].as_u64(), Some(i as u64));
            (
                e["object_id"].as_str().unwrap().to_string(),
                e["class"].as_str().unwrap().to_string(),
                e["level"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    Truth {
        pos: g
            .positions
            .iter()
            .map(|p| DVec3::from(p.map(f64::from)))
            .collect(),
        sigma: g
            .scale
            .iter()
            .map(|s| f64::from(s[0].max(s[1]).max(s[2])).exp())
            .collect(),
        log_scale: g.scale.clone(),
        rot: g.rotation.clone(),
        opacity: g
            .opacity
            .iter()
            .map(|o| 1.0 / (1.0 + (-f64::from(*o)).exp()))
            .collect(),
        class: col("class"),
        feature: col("feature_id"),
        surface: col("surface_id"),
        part: col("part_id"),
        entities,
    }
}

impl Truth {
    /// The (level, class, gml:id) chain of Gaussian `i`: building → surface → part.
    fn chain(&self, i: usize) -> Vec<(String, String, String)> {
        [self.feature[i], self.surface[i], self.part[i]]
            .into_iter()
            .filter(|&e| e >= 0)
            .map(|e| {
                let (id, class, level) = &self.entities[e as usize];
                (level.clone(), class.clone(), id.clone())
            })
            .collect()
    }
}

#[test]
fn listens_on_loopback_only() {
    let srv = Server::start(run_dir());
    assert!(srv.url.starts_with("http://127.0.0.1:"), "{}", srv.url);
    // The kernel's table of listening sockets: every listener on the port is 127.0.0.1.
    let hex_port = format!(":{:04X}", srv.port);
    let tcp = std::fs::read_to_string("/proc/net/tcp").unwrap();
    let listeners: Vec<&str> = tcp
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (f[1].ends_with(&hex_port) && f[3] == "0A").then_some(f[1])
        })
        .collect();
    assert_eq!(listeners, vec![format!("0100007F{hex_port}")], "{tcp}");
    let tcp6 = std::fs::read_to_string("/proc/net/tcp6").unwrap_or_default();
    assert!(
        !tcp6.lines().skip(1).any(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            f[1].ends_with(&hex_port) && f[3] == "0A"
        }),
        "no IPv6 listener on the port"
    );
    // From another local address of the machine the port is closed.
    let other = UdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0))
        .and_then(|u| u.connect(("10.255.255.255", 9)).map(|_| u))
        .and_then(|u| u.local_addr())
        .ok()
        .map(|a| a.ip())
        .filter(|ip| !ip.is_loopback() && !ip.is_unspecified());
    if let Some(ip) = other {
        let r = TcpStream::connect_timeout(&SocketAddr::new(ip, srv.port), Duration::from_secs(3));
        assert!(r.is_err(), "{ip}:{} accepted a connection", srv.port);
    }
    assert_eq!(srv.get("/api/meta").0, 200);
}

#[test]
fn refuses_paths_outside_the_run_folder() {
    let run = run_dir();
    let scene = run.parent().unwrap().join("scene");
    for (link, to) in [
        ("view-link-out", scene.clone()),
        ("view-link-in", run.join("lift")),
    ] {
        match std::os::unix::fs::symlink(&to, run.join(link)) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => panic!("{link}: {e}"),
        }
    }
    let srv = Server::start(run);
    for target in [
        "/files/../run.json",
        "/files/../scene/summary.json",
        "/files/%2e%2e/scene/summary.json",
        "/files/%2E%2E%2Fscene%2Fsummary.json",
        "/files/lift/%2e%2e/%2e%2e/scene/summary.json",
        "/files/lift/..%2f..%2fscene%2fsummary.json",
        "/files//etc/passwd",
        "/files/%2Fetc%2Fpasswd",
        "/files/./run.json",
        "/files/lift%5c..%5c..%5cscene%5csummary.json",
        "/files/view-link-out/summary.json",
        "/files/view-link-out/point_cloud.ply",
    ] {
        let (s, b) = srv.get(target);
        assert_eq!(s, 403, "{target}: {}", String::from_utf8_lossy(&b));
    }
    for target in [
        "/../run.json",
        "/../../etc/passwd",
        "/files/lift",
        "/files/nothing",
    ] {
        let (s, _) = srv.get(target);
        assert_eq!(s, 404, "{target}");
    }
    // Inside the run folder, through a link that stays inside too: the file's bytes.
    for (target, file) in [
        ("/files/run.json", run.join("run.json")),
        ("/files/lift/summary.json", run.join("lift/summary.json")),
        (
            "/files/view-link-in/summary.json",
            run.join("lift/summary.json"),
        ),
        ("/files/report.html", run.join("report.html")),
    ] {
        let (s, b) = srv.get(target);
        assert_eq!(s, 200, "{target}");
        assert_eq!(b, std::fs::read(&file).unwrap(), "{target}");
    }
}

#[test]
fn survives_malformed_requests() {
    let run = run_dir();
    let srv = Server::start(run);
    let host = format!("Host: 127.0.0.1:{}\r\n", srv.port);
    // Garbage bytes.
    let garbage: Vec<u8> = (0..4096u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    assert_eq!(srv.raw(&garbage).0, 400);
    assert_eq!(srv.raw(b"\x00\x01\x02\r\n\r\n").0, 400);
    // A 200 KB header, and 100 headers.
    let mut big = format!("GET /api/meta HTTP/1.1\r\n{host}X-Big: ").into_bytes();
    big.extend(std::iter::repeat_n(b'a', 200_000));
    big.extend_from_slice(b"\r\n\r\n");
    assert_eq!(srv.raw(&big).0, 431);
    let many: String = (0..100).map(|i| format!("X-H{i}: {i}\r\n")).collect();
    assert_eq!(
        srv.raw(format!("GET /api/meta HTTP/1.1\r\n{host}{many}\r\n").as_bytes())
            .0,
        431
    );
    // Connections that end early or say nothing useful.
    drop(TcpStream::connect(("127.0.0.1", srv.port)).unwrap());
    {
        let mut s = TcpStream::connect(("127.0.0.1", srv.port)).unwrap();
        s.write_all(b"GET /api/me").unwrap();
    }
    assert_eq!(
        srv.raw(
            format!("POST /api/meta HTTP/1.1\r\n{host}Content-Length: 5\r\n\r\nhello").as_bytes()
        )
        .0,
        405
    );
    assert_eq!(
        srv.raw(b"GET /api/meta HTTP/1.1\r\nHost: evil.example\r\n\r\n")
            .0,
        421
    );
    assert_eq!(srv.get("/api/query?where=%zz").0, 400);
    assert_eq!(srv.get("/api/query").0, 400);
    assert_eq!(srv.get("/api/pick?i=abc").0, 400);
    assert_eq!(srv.get("/api/pick?i=-1").0, 400);
    assert_eq!(srv.get("/api/pick?i=99999999999").0, 404);
    // Bad query syntax: 400 with the parser's message, the one `gs4city query` prints.
    for q in ["class=", "class=Window and (", "measuredHeight >> 3", "not"] {
        let (s, j) = srv.get_json(&format!("/api/query?where={}", enc(q)));
        assert_eq!(s, 400, "{q}: {j}");
        let server = j["error"].as_str().unwrap();
        let cli = cli_count(run, q).expect_err(q);
        let tail = |m: &str| {
            m.split_once(&format!("`{q}`: "))
                .map(|(_, t)| t.trim().to_string())
                .unwrap_or_else(|| panic!("{q}: no parser message in `{m}`"))
        };
        assert_eq!(tail(server), tail(&cli), "{q}");
        assert!(server.contains("column"), "{server}");
    }
    // 3000 nested `(` in one 6 KB request overflowed the server thread's stack and killed the
    // viewer: now a 400 naming the bound.
    let (open, close) = ("(".repeat(3000), ")".repeat(3000));
    let (s, j) = srv.get_json(&format!(
        "/api/query?where={open}{}{close}",
        enc("class=Window")
    ));
    assert_eq!(s, 400, "{j}");
    assert!(
        j["error"]
            .as_str()
            .unwrap()
            .contains("nested deeper than 128"),
        "{j}"
    );
    // Still serving.
    let (s, meta) = srv.get_json("/api/meta");
    assert_eq!(s, 200);
    assert!(meta["gaussians"].as_u64().unwrap() > 1000);
}

/// `/api/query` selects, Gaussian for Gaussian, what an independent reading of the expression
/// over `semantic.ply` (plyfile) and `semantics.json` selects (`selection_reference`), for every
/// expression; and the window class column of `semantic.ply` is `class=Window`.
#[test]
fn query_api_selects_what_semantic_ply_holds() {
    const TEST: &str = "view::query_api_selects_what_semantic_ply_holds";
    let queries = [
        "class=Window",
        "level=part",
        "class=Building and measuredHeight > 15",
        "class=WallSurface or class=RoofSurface",
        "not class=Building",
        "id=\"4018106\" or within(\"4018106_BP.vaTC1d8GxA5iZnJavLPU\")",
        "text(\"a tree\")",
    ];
    let run = run_dir();
    let Some(want) = reference_selections(TEST, run, &queries) else {
        return;
    };
    let t = truth(run);
    let srv = Server::start(run);
    for (q, want) in queries.iter().zip(&want) {
        let (s, j) = srv.get_json(&format!("/api/query?where={}", enc(q)));
        assert_eq!(s, 200, "{q}: {j}");
        let count = j["count"].as_u64().unwrap() as usize;
        let mask = base64_decode(j["mask"].as_str().unwrap());
        assert_eq!(mask.len(), t.class.len().div_ceil(8), "{q}");
        let bits: Vec<usize> = (0..t.class.len())
            .filter(|&i| mask[i / 8] >> (i % 8) & 1 == 1)
            .collect();
        assert_eq!(bits.len(), count, "{q}");
        assert!(
            &bits == want,
            "{q}: {count} selected, the reference {}",
            want.len()
        );
        assert!(count > 100, "{q}: {count}");
        if *q == "class=Window" {
            let windows: Vec<usize> = (0..t.class.len()).filter(|&i| t.class[i] == 2).collect();
            assert_eq!(
                bits, windows,
                "class=Window: the Gaussians of class window in semantic.ply"
            );
        }
    }
}

/// Standard base64 (with padding), written here from RFC 4648.
fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let mut out = Vec::new();
    for q in s.as_bytes().chunks(4) {
        let pad = q.iter().filter(|&&c| c == b'=').count();
        let v = q
            .iter()
            .map(|&c| if c == b'=' { 0 } else { val(c) })
            .fold(0u32, |a, x| a << 6 | x);
        out.extend_from_slice(&[(v >> 16) as u8, (v >> 8) as u8, v as u8][..3 - pad]);
    }
    out
}

/// The string fields `keys` of each object of JSON array `a`.
fn triples(a: &Value, keys: [&str; 3]) -> Vec<(String, String, String)> {
    let f = |e: &Value, k: &str| {
        e[k].as_str()
            .unwrap_or_else(|| panic!("no {k} in {e}"))
            .to_string()
    };
    a.as_array()
        .unwrap_or_else(|| panic!("not an array: {a}"))
        .iter()
        .map(|e| (f(e, keys[0]), f(e, keys[1]), f(e, keys[2])))
        .collect()
}

#[test]
fn pick_api_reports_the_hierarchy_of_semantic_ply() {
    let run = run_dir();
    let t = truth(run);
    let srv = Server::start(run);
    let n = t.class.len();
    let mut checked_parts = 0;
    for i in (0..n)
        .step_by(617)
        .chain((0..n).filter(|&i| t.part[i] >= 0).step_by(97))
    {
        let (s, j) = srv.get_json(&format!("/api/pick?i={i}"));
        assert_eq!(s, 200);
        assert_eq!(j["gaussian"].as_u64(), Some(i as u64));
        assert_eq!(
            j["class"].as_i64(),
            Some(i64::from(t.class[i])),
            "Gaussian {i}"
        );
        let got = triples(&j["chain"], ["level", "class", "object_id"]);
        assert_eq!(got, t.chain(i), "Gaussian {i}");
        checked_parts += usize::from(t.part[i] >= 0);
    }
    assert!(checked_parts > 20, "{checked_parts}");
}

/// The largest eigenvector of a symmetric 3×3 matrix (power iteration).
fn principal(m: glam::DMat3, avoid: Option<DVec3>) -> DVec3 {
    let mut v = DVec3::new(0.577, 0.577, 0.577);
    for _ in 0..200 {
        let mut w = m * v;
        if let Some(a) = avoid {
            w -= a * w.dot(a);
        }
        v = w.normalize_or(DVec3::X);
    }
    v
}

/// A window to click on: its part entity, the Gaussian to click, the camera eye and target.
/// The camera looks at the window's centre along its normal (from outside its building); the
/// window is taken only when every drawn Gaussian that could cover the clicked pixel in front
/// of the clicked Gaussian belongs to the window too.
fn window_shot(t: &Truth) -> (i32, usize, DVec3, DVec3) {
    let mut parts: std::collections::BTreeMap<i32, Vec<usize>> = Default::default();
    for (i, &p) in t.part.iter().enumerate() {
        if p >= 0 && t.entities[p as usize].1 == "Window" {
            parts.entry(p).or_default().push(i);
        }
    }
    let mut order: Vec<(i32, Vec<usize>)> = parts.into_iter().collect();
    order.sort_by_key(|(p, g)| (std::cmp::Reverse(g.len()), *p));
    for (p, gs) in order {
        let c = gs.iter().map(|&i| t.pos[i]).sum::<DVec3>() / gs.len() as f64;
        let cov = gs.iter().fold(glam::DMat3::ZERO, |m, &i| {
            let d = t.pos[i] - c;
            m + glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z)
        }) * (1.0 / gs.len() as f64);
        let a1 = principal(cov, None);
        let a2 = principal(cov, Some(a1));
        let mut normal = a1.cross(a2).normalize();
        let b = t.feature[gs[0]];
        let bg: Vec<usize> = (0..t.pos.len()).filter(|&i| t.feature[i] == b).collect();
        let bc = bg.iter().map(|&i| t.pos[i]).sum::<DVec3>() / bg.len() as f64;
        if normal.dot(c - bc) < 0.0 {
            normal = -normal;
        }
        let extent = (cov * a1).length().sqrt() * 2.0;
        let g = *gs
            .iter()
            .min_by(|&&i, &&j| (t.pos[i] - c).length().total_cmp(&(t.pos[j] - c).length()))
            .unwrap();
        let eye = c + normal * (3.0 * extent).max(2.0);
        let ray = (t.pos[g] - eye).normalize();
        let tg = (t.pos[g] - eye).dot(ray);
        let clear = (0..t.pos.len()).all(|i| {
            let d = t.pos[i] - eye;
            let along = d.dot(ray);
            let off = (d - ray * along).length();
            t.opacity[i] < 0.05
                || along <= 0.0
                || along > tg + 0.05
                || off > 2.0 * t.sigma[i] + 0.02
                || t.part[i] == p
        });
        if clear {
            return (p, g, eye, c);
        }
    }
    panic!("no window of the run is clear to click on");
}

/// `tools/js` when the browser tests can run (playwright-core installed, Debian's Chromium
/// present); else the test is skipped with the reason.
fn browser_tools(test: &str) -> Option<std::path::PathBuf> {
    let tools = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/js");
    if !tools.join("node_modules/playwright-core").is_dir() {
        crate::common::skip(
            test,
            "tools/js/node_modules/playwright-core is missing (scripts/setup.sh runs npm ci in tools/js)",
        );
        return None;
    }
    if !Path::new("/usr/bin/chromium").is_file() {
        crate::common::skip(
            test,
            "/usr/bin/chromium is missing (scripts/setup.sh installs Debian's chromium)",
        );
        return None;
    }
    Some(tools)
}

#[test]
fn click_on_a_window_and_type_queries_in_headless_chromium() {
    let test = "view::click_on_a_window_and_type_queries_in_headless_chromium";
    let Some(tools) = browser_tools(test) else {
        return;
    };
    let run = run_dir();
    let t = truth(run);
    let (part, g, eye, target) = window_shot(&t);
    let expected = t.chain(g);
    assert_eq!(
        expected.iter().map(|e| e.0.as_str()).collect::<Vec<_>>(),
        ["feature", "surface", "part"]
    );
    let queries = [
        "class=Window",
        "class=WallSurface or class=RoofSurface",
        "class=Building and measuredHeight > 15",
        "class=",
    ];
    let srv = Server::start(run);
    let dir = run.parent().unwrap();
    let shot = dir.join("view.png");
    let spec = serde_json::json!({
        "url": srv.url,
        "eye": eye.to_array(),
        "target": target.to_array(),
        "click": t.pos[g].to_array(),
        "queries": queries,
        "screenshot": shot,
        "screenshot_query": "class=Window",
        "screenshot_overview": true,
        "width": 960,
        "height": 640,
    });
    let spec_path = dir.join("click-spec.json");
    std::fs::write(&spec_path, spec.to_string()).unwrap();
    let o = Command::new("node")
        .arg(tools.join("view_click.mjs"))
        .arg(&spec_path)
        .current_dir(&tools)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "node: {stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let r: Value = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    assert!(r["error"].is_null(), "{r}");
    assert_eq!(r["gaussians"].as_u64(), Some(t.pos.len() as u64));
    assert_eq!(r["renderer"].as_str(), Some("spark"), "{r}");
    // Spark drew the window where the camera sees it: in the Class mode the pixels around the
    // clicked point are nearer the window's class colour than any other class colour or the
    // background, and the RGB mode drew something else there.
    let near = |rgb: &Value| -> (usize, f64) {
        let c: Vec<f64> = (0..3).map(|k| rgb[k].as_f64().unwrap()).collect();
        let mut cands: Vec<[u8; 3]> = (0..classes::NAMES.len() as i32)
            .map(classes::color)
            .collect();
        cands.push([0x1c, 0x20, 0x25]);
        let d = |p: &[u8; 3]| {
            (0..3)
                .map(|k| (c[k] - f64::from(p[k])).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        let best = (0..cands.len())
            .min_by(|&a, &b| d(&cands[a]).total_cmp(&d(&cands[b])))
            .unwrap();
        (best, d(&cands[best]))
    };
    let (cls, dist) = near(&r["class_at_click"]["rgb"]);
    assert_eq!(
        cls, 2,
        "Spark's colour at the window is not the window class colour: {r}"
    );
    assert!(dist < 60.0, "{r}");
    assert_ne!(r["rgb_at_click"]["rgb"], r["class_at_click"]["rgb"], "{r}");
    // The overview shows the scene: most of the canvas is drawn, not background.
    let bg = r["overview"]["background_share"].as_f64().unwrap();
    assert!(bg < 0.75, "the overview is {bg} background: {r}");
    // The click: a Gaussian of the window, and the panel shows the window, its wall, its building.
    let picked = r["picked_gaussian"].as_i64().unwrap();
    assert!(picked >= 0, "the click hit nothing: {r}");
    assert_eq!(
        t.part[picked as usize], part,
        "picked Gaussian {picked}: {r}"
    );
    let panel = triples(&r["panel"], ["level", "class", "gml_id"]);
    assert_eq!(panel, expected, "{r}");
    assert_eq!(panel[0].1, "Building");
    assert_eq!(panel[1].1, "WallSurface");
    assert_eq!(panel[2].1, "Window");
    // The queries typed in the box: the highlighted count is what an independent reading of
    // `semantic.ply` selects (`selection_reference`); the bad one shows the parser's message.
    let valid = &queries[..3];
    let want = reference_selections(test, run, valid);
    for (q, shown) in queries.iter().zip(r["queries"].as_array().unwrap()) {
        match valid.iter().position(|v| v == q) {
            Some(k) => {
                if let Some(want) = &want {
                    let n = want[k].len() as u64;
                    assert_eq!(shown["count"].as_u64(), Some(n), "{q}: {shown}");
                }
                assert_eq!(shown["error"].as_str(), Some(""), "{q}");
            }
            None => {
                let e = cli_count(run, q).expect_err(q);
                assert!(shown["count"].is_null(), "{q}: {shown}");
                let msg = shown["error"].as_str().unwrap();
                assert!(
                    !msg.is_empty() && e.contains(msg.split_once("`: ").unwrap().1.trim()),
                    "{q}: page `{msg}`, CLI `{e}`"
                );
            }
        }
    }
    let png = std::fs::read(&shot).unwrap();
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000);
    // GS4CITY_VIEW_PNG=docs/img/view.png keeps the screenshot (docs/view.md).
    if let Some(keep) = std::env::var_os("GS4CITY_VIEW_PNG") {
        std::fs::write(keep, &png).unwrap();
    }
}

/// `gs4city view --scene S` (no run) in headless Chromium: the page shows the scene in RGB
/// without the run's buttons, and a real mouse click on a window shows the clicked point's scene
/// coordinates and lists them — the point on the clicked Gaussian's splat surface, on the ray
/// through the clicked pixel (within 1 cm of it, checked here from the page's camera matrix), and
/// within the clicked Gaussian's reach (2σ + 5 cm) of its centre; the server's `/api/point` for
/// the same camera and position answers the same point.
#[test]
fn a_click_in_view_scene_shows_the_point_in_headless_chromium() {
    let test = "view::a_click_in_view_scene_shows_the_point_in_headless_chromium";
    let Some(tools) = browser_tools(test) else {
        return;
    };
    let run = run_dir();
    let t = truth(run);
    let (_, g, eye, target) = window_shot(&t);
    let scene = run.parent().unwrap().join("scene");
    let srv = Server::start_with(&["--scene", scene.to_str().unwrap()]);
    let (st, meta) = srv.get_json("/api/meta");
    assert_eq!(st, 200);
    assert!(meta["run"].is_null(), "{meta}");
    let (st, _) = srv.get_json("/api/pick?i=0");
    assert_eq!(st, 404, "no run: no hierarchy to pick");
    let dir = run.parent().unwrap();
    let spec = serde_json::json!({
        "url": srv.url,
        "eye": eye.to_array(),
        "target": target.to_array(),
        "click": t.pos[g].to_array(),
        "queries": [],
        "scene_only": true,
        "screenshot": dir.join("view-scene.png"),
        "width": 960,
        "height": 640,
    });
    let spec_path = dir.join("click-scene-spec.json");
    std::fs::write(&spec_path, spec.to_string()).unwrap();
    let o = Command::new("node")
        .arg(tools.join("view_click.mjs"))
        .arg(&spec_path)
        .current_dir(&tools)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "node: {stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let r: Value = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    assert!(r["error"].is_null(), "{r}");
    assert!(r["status"].as_str().unwrap().contains("no run yet"), "{r}");
    let p = &r["point"];
    assert_eq!(p["hit"], true, "{r}");
    assert_eq!(
        p["buttons_shown"], false,
        "the run's colour buttons are hidden: {r}"
    );
    let xyz: Vec<f64> = (0..3).map(|k| p["scene"][k].as_f64().unwrap()).collect();
    let q = DVec3::new(xyz[0], xyz[1], xyz[2]);
    // On the ray from the eye through the clicked Gaussian (the click is that Gaussian's pixel,
    // rounded to a CSS pixel by the mouse: within 1 cm at this distance).
    let ray = (t.pos[g] - eye).normalize();
    let off = ((q - eye) - ray * (q - eye).dot(ray)).length();
    assert!(
        off < 0.01 * (t.pos[g] - eye).length(),
        "{off} off the ray: {r}"
    );
    assert!(
        (q - t.pos[g]).length() < 2.0 * t.sigma[g] + 0.05,
        "{q} vs the clicked Gaussian at {} (σ {}): {r}",
        t.pos[g],
        t.sigma[g]
    );
    // Shown and listed with 4 decimals.
    let text = p["text"].as_str().unwrap();
    assert!(text.contains(&format!("{:.4}", q.x)), "{text}");
    assert!(
        p["list"]
            .as_str()
            .unwrap()
            .contains(&format!("{:.4} {:.4} {:.4}", q.x, q.y, q.z))
    );
    // The API for the same camera and position: the same point.
    let up: Vec<f64> = (0..3).map(|k| meta["up"][k].as_f64().unwrap()).collect();
    let px = &r["pixel"];
    let (st, j) = srv.get_json(&format!(
        "/api/point?eye={},{},{}&target={},{},{}&up={},{},{}&fovy=50&width=960&height=640&x={}&y={}",
        eye.x, eye.y, eye.z, target.x, target.y, target.z, up[0], up[1], up[2],
        px[0].as_f64().unwrap(), px[1].as_f64().unwrap()
    ));
    assert_eq!(st, 200, "{j}");
    let a: Vec<f64> = (0..3).map(|k| j["scene"][k].as_f64().unwrap()).collect();
    assert!(
        (DVec3::new(a[0], a[1], a[2]) - q).length() < 0.01,
        "{j} vs {r}"
    );
}

/// `/api/point` refuses what it cannot answer, each with its reason: a missing parameter, a
/// view that is not the scene's, a position outside the image.
#[test]
fn point_api_names_what_is_wrong() {
    let srv = Server::start(run_dir());
    for (q, want) in [
        ("x=1&y=1", "eye"),
        ("view=nope&x=1&y=1", "nope"),
        (
            "eye=0,0,0&target=0,0,1&up=0,1,0&fovy=50&width=10&height=10&x=11&y=1",
            "outside",
        ),
        (
            "eye=0,0,0&target=0,0,1&up=0,1,0&fovy=500&width=10&height=10&x=1&y=1",
            "fovy",
        ),
        (
            "eye=0,0,0&target=0,0,0&up=0,1,0&fovy=50&width=10&height=10&x=1&y=1",
            "eye equals target",
        ),
        (
            "eye=0,0,nan&target=0,0,1&up=0,1,0&fovy=50&width=10&height=10&x=1&y=1",
            "eye",
        ),
    ] {
        let (st, j) = srv.get_json(&format!("/api/point?{q}"));
        assert_eq!(st, 400, "{q}: {j}");
        assert!(j["error"].as_str().unwrap().contains(want), "{q}: {j}");
    }
    // A view of the scene: the centre pixel of its first view hits something or says why not.
    let (st, j) = srv.get_json("/api/point?view=orbit_000&x=10.5&y=10.5");
    assert_eq!(st, 200, "{j}");
    assert!(j["hit"].is_boolean(), "{j}");
}

/// `/api/splats.bin` (version 3) holds what Spark draws: per Gaussian the centre, σ, the three
/// activated scales and the unit quaternion in Spark's `x y z w` order, checked against the
/// raw `semantic.ply` columns (exp of the log scales, the quaternion normalised here), and, the
/// run being within the splat budget, each splat standing for its own Gaussian.
#[test]
fn splats_binary_holds_centres_scales_and_rotations() {
    let run = run_dir();
    let t = truth(run);
    let srv = Server::start(run);
    let (status, b) = srv.get("/api/splats.bin");
    assert_eq!(status, 200);
    let n = t.pos.len();
    assert_eq!(&b[..4], b"GS4V");
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    assert_eq!((u32_at(4), u32_at(8) as usize), (3, n));
    assert_eq!(b.len(), 16 + 60 * n);
    for i in 0..n {
        assert_eq!(u32_at(16 + 56 * n + 4 * i) as usize, i);
    }
    let f = |o: usize| f64::from(f32::from_le_bytes(b[o..o + 4].try_into().unwrap()));
    let (pos, sig, scl, rot) = (16, 16 + 12 * n, 16 + 16 * n, 16 + 28 * n);
    for i in (0..n).step_by(97) {
        for k in 0..3 {
            assert_eq!(f(pos + 12 * i + 4 * k), t.pos[i][k], "x{k} of {i}");
            let e = f64::from(t.log_scale[i][k]).exp();
            assert!(
                (f(scl + 12 * i + 4 * k) - e).abs() <= 1e-5 * e,
                "scale {k} of {i}"
            );
        }
        assert!(
            (f(sig + 4 * i) - t.sigma[i]).abs() <= 1e-5 * t.sigma[i],
            "σ of {i}"
        );
        let q = t.rot[i].map(f64::from);
        let l = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        for (k, raw) in [q[1], q[2], q[3], q[0]].into_iter().enumerate() {
            assert!(
                (f(rot + 16 * i + 4 * k) - raw / l).abs() < 1e-6,
                "quaternion {k} of {i}"
            );
        }
    }
}

/// A run of more Gaussians than the splat budget (`view --max-splats 20000` on the 131 154 of
/// the small run) is served as at most that many splats, each standing for one Gaussian of the
/// run, with that Gaussian's class colour and building colour (semantic.ply's class column
/// through the palette of docs/design.md, by hand), inside the run's bounds; every Gaussian
/// stands behind at most one splat; `/api/meta` gives both counts, and `/api/query` still counts
/// and masks every Gaussian (the `class=Window` bitmask equals semantic.ply's window column).
#[test]
fn a_run_beyond_the_budget_is_served_as_a_coarse_set_standing_for_its_gaussians() {
    let run = run_dir();
    let t = truth(run);
    let srv = Server::start_with(&["--run", run.to_str().unwrap(), "--max-splats", "20000"]);
    let (status, meta) = srv.get("/api/meta");
    assert_eq!(status, 200);
    let meta: Value = serde_json::from_slice(&meta).unwrap();
    let n_all = t.pos.len();
    assert_eq!(meta["gaussians"].as_u64(), Some(n_all as u64));
    let (_, b) = srv.get("/api/splats.bin");
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let n = u32_at(8) as usize;
    assert_eq!(meta["splats"].as_u64(), Some(n as u64));
    assert!(n <= 20_000 && n > 5_000, "{n} splats");
    assert_eq!(b.len(), 16 + 60 * n);
    // The class palette of docs/design.md, by hand.
    let palette: [[u8; 3]; 12] = [
        [200, 180, 140],
        [180, 60, 50],
        [60, 140, 230],
        [240, 160, 40],
        [120, 100, 80],
        [170, 90, 200],
        [40, 160, 60],
        [250, 60, 160],
        [230, 230, 30],
        [90, 90, 90],
        [30, 200, 220],
        [255, 255, 255],
    ];
    let (cls, idx) = (16 + 48 * n, 16 + 56 * n);
    let mut seen = vec![false; n_all];
    let f = |o: usize| f64::from(f32::from_le_bytes(b[o..o + 4].try_into().unwrap()));
    let (lo, hi) = t.pos.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    for i in 0..n {
        let g = u32_at(idx + 4 * i) as usize;
        assert!(g < n_all && !seen[g], "splat {i} stands for {g}");
        seen[g] = true;
        let c = t.class[g];
        if c >= 0 {
            assert_eq!(
                &b[cls + 4 * i..cls + 4 * i + 3],
                &palette[c as usize],
                "splat {i}"
            );
        }
        let p = DVec3::new(f(16 + 12 * i), f(20 + 12 * i), f(24 + 12 * i));
        assert!(p.cmpge(lo - 1e-3).all() && p.cmple(hi + 1e-3).all(), "{p}");
    }
    let (status, q) = srv.get("/api/query?where=category%3Dwindow");
    assert_eq!(status, 200);
    let q: Value = serde_json::from_slice(&q).unwrap();
    let want = t.class.iter().filter(|&&c| c == 2).count();
    assert_eq!(q["count"].as_u64(), Some(want as u64));
}

/// The renderer embedded in the binary and served under `/vendor/` is byte for byte the npm
/// packages pinned in tools/js (`@sparkjsdev/spark`, `three`), with their licence files.
#[test]
fn vendored_renderer_is_the_npm_package() {
    let test = "view::vendored_renderer_is_the_npm_package";
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let nm = root.join("tools/js/node_modules");
    if !nm.join("@sparkjsdev/spark").is_dir() || !nm.join("three").is_dir() {
        crate::common::skip(
            test,
            "tools/js/node_modules has no @sparkjsdev/spark or three (scripts/setup.sh runs npm ci in tools/js)",
        );
        return;
    }
    let lock: Value = serde_json::from_str(
        &std::fs::read_to_string(root.join("tools/js/package-lock.json")).unwrap(),
    )
    .unwrap();
    for (pkg, version) in [("@sparkjsdev/spark", "2.2.0"), ("three", "0.180.0")] {
        let installed: Value = serde_json::from_str(
            &std::fs::read_to_string(nm.join(pkg).join("package.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(installed["version"].as_str(), Some(version), "{pkg}");
        assert_eq!(
            lock["packages"][format!("node_modules/{pkg}")]["version"].as_str(),
            Some(version),
            "{pkg} in package-lock.json"
        );
    }
    let srv = Server::start(run_dir());
    for (url, npm) in [
        (
            "/vendor/spark.module.min.js",
            "@sparkjsdev/spark/dist/spark.module.min.js",
        ),
        ("/vendor/LICENSE.spark", "@sparkjsdev/spark/LICENSE"),
        (
            "/vendor/three.module.min.js",
            "three/build/three.module.min.js",
        ),
        ("/vendor/three.core.min.js", "three/build/three.core.min.js"),
        (
            "/vendor/three/addons/postprocessing/Pass.js",
            "three/examples/jsm/postprocessing/Pass.js",
        ),
        ("/vendor/LICENSE.three", "three/LICENSE"),
    ] {
        let want = std::fs::read(nm.join(npm)).unwrap();
        let vendored =
            std::fs::read(root.join("src/view").join(url.trim_start_matches('/'))).unwrap();
        assert!(
            vendored == want,
            "src/view{url} differs from node_modules/{npm}"
        );
        let (status, text, body) = srv.raw(
            format!(
                "GET {url} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n\r\n",
                srv.port
            )
            .as_bytes(),
        );
        assert_eq!(status, 200, "{url}");
        assert!(
            body == want,
            "{url}: the served bytes differ from node_modules/{npm}"
        );
        let ct = if url.ends_with(".js") {
            "text/javascript"
        } else {
            "text/plain"
        };
        assert!(
            text.lines()
                // Header names are case-insensitive (RFC 9110 §5.1); hyper writes them lower-case.
                .any(|l| l.to_ascii_lowercase().starts_with("content-type: ") && l.contains(ct)),
            "{url}: not {ct}"
        );
    }
}

/// The server's resident memory in kB (`VmRSS` of /proc/PID/status).
fn rss_kb(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap()
}

/// Slow clients cannot hold the server: 40 connections that send a partial request head,
/// trickle one more header byte every 200 ms and reconnect as soon as they are closed, for
/// 20 s (`GS4CITY_SLOW_CLIENT_S` seconds where set; at least 6 for the deadline checks). Meanwhile
/// a normal client's requests all succeed, 99 % of them within 1 s; each slow connection is closed
/// by the head deadline (5 s from its start, however it trickles: `408`); the server's resident
/// memory stays within 64 MB of what it was before; beyond the connection limit a client gets
/// `503` with `Retry-After`. A load generator of its own (raw sockets), no mock of the server.
#[test]
fn slow_clients_cannot_hold_the_server() {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    use std::sync::{Arc, Mutex};
    use std::time::Instant;
    let window = std::env::var("GS4CITY_SLOW_CLIENT_S")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20u64);
    let srv = Server::start(run_dir());
    let (port, pid) = (srv.port, srv.child.id());
    // Warm: the first requests map the page and the splats.
    assert_eq!(srv.get("/api/meta").0, 200);
    assert_eq!(srv.get("/api/splats.bin").0, 200);
    let rss0 = rss_kb(pid);
    let stop = Arc::new(AtomicBool::new(false));
    let reopened = Arc::new(AtomicUsize::new(0));
    // Per closed slow connection: how long it had lived, and what it was answered.
    let lifetimes = Arc::new(Mutex::new(Vec::<(f64, String)>::new()));
    let slow: Vec<_> = (0..40)
        .map(|_| {
            let (stop, reopened, lifetimes) = (
                Arc::clone(&stop),
                Arc::clone(&reopened),
                Arc::clone(&lifetimes),
            );
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) else {
                        continue;
                    };
                    reopened.fetch_add(1, Ordering::Relaxed);
                    let t0 = Instant::now();
                    let _ = s.set_read_timeout(Some(Duration::from_millis(200)));
                    let _ = s.write_all(
                        format!("GET /api/meta HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Slow: ")
                            .as_bytes(),
                    );
                    let mut answer = Vec::new();
                    loop {
                        if stop.load(Ordering::Relaxed) {
                            return;
                        }
                        // One more byte of the header value, then see whether the server closed.
                        if s.write_all(b"a").is_err() {
                            break;
                        }
                        let mut buf = [0u8; 512];
                        match s.read(&mut buf) {
                            Ok(0) => break,
                            Ok(n) => answer.extend_from_slice(&buf[..n]),
                            Err(e)
                                if e.kind() == std::io::ErrorKind::WouldBlock
                                    || e.kind() == std::io::ErrorKind::TimedOut => {}
                            Err(_) => break,
                        }
                    }
                    let first = String::from_utf8_lossy(&answer)
                        .lines()
                        .next()
                        .unwrap_or("")
                        .to_string();
                    lifetimes
                        .lock()
                        .unwrap()
                        .push((t0.elapsed().as_secs_f64(), first));
                }
            })
        })
        .collect();
    // The normal client, one request after the other, for the window.
    let t0 = Instant::now();
    let mut latencies = Vec::new();
    let mut peak = rss0;
    while t0.elapsed() < Duration::from_secs(window) {
        let t = Instant::now();
        let (status, body) = srv.get("/api/meta");
        latencies.push(t.elapsed().as_secs_f64());
        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
        peak = peak.max(rss_kb(pid));
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::Relaxed);
    for t in slow {
        t.join().unwrap();
    }
    latencies.sort_by(f64::total_cmp);
    let p = |q: f64| latencies[((latencies.len() - 1) as f64 * q).round() as usize];
    let closed = lifetimes.lock().unwrap().clone();
    let longest = closed.iter().map(|c| c.0).fold(0.0, f64::max);
    eprintln!(
        "slow clients: {window} s, {} connections opened, {} closed by the server (longest {longest:.2} s); \
         normal client: {} requests, p50 {:.3} s, p99 {:.3} s, max {:.3} s; server RSS {} → {} kB",
        reopened.load(Ordering::Relaxed),
        closed.len(),
        latencies.len(),
        p(0.5),
        p(0.99),
        p(1.0),
        rss0,
        peak
    );
    assert!(p(0.99) <= 1.0, "p99 {:.3} s", p(0.99));
    assert!(peak <= rss0 + 64 * 1024, "RSS {rss0} → {peak} kB");
    if window >= 6 {
        // Every slow connection that lived to the deadline was closed by it, with a 408.
        assert!(
            closed.len() >= 40,
            "{} slow connections closed",
            closed.len()
        );
        assert!(
            longest < 7.0,
            "a slow head held its connection {longest:.2} s"
        );
        assert!(
            closed.iter().all(|c| c.1.starts_with("HTTP/1.1 408")),
            "{:?}",
            closed.iter().find(|c| !c.1.starts_with("HTTP/1.1 408"))
        );
    }
    // Beyond the connection limit: 503 with Retry-After, and the server recovers.
    let idle: Vec<TcpStream> = (0..512)
        .filter_map(|_| TcpStream::connect(("127.0.0.1", port)).ok())
        .collect();
    assert_eq!(idle.len(), 512);
    std::thread::sleep(Duration::from_millis(300));
    let (status, text, _) =
        srv.raw(format!("GET /api/meta HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").as_bytes());
    assert_eq!(status, 503, "{text}");
    assert!(text.contains("Retry-After: 1\r\n"), "{text}");
    drop(idle);
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(srv.get("/api/meta").0, 200);
}
