//! The layering rule of ARCHITECTURE.md, checked on the source: every top-level module of
//! `src/` is listed in the module table with its kind, and its `crate::` imports obey the
//! layers — formats and library modules (the ground floor) import no stage, a stage imports no
//! other stage, the orchestrators (`run`, `synth`) import no orchestrator, only `cli` imports
//! everything — the import graph has no circle, and the table's "depends on" column names every
//! module a module imports. The expectation is the table as written by hand; the imports are read
//! from the source text, independently of the compiler.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The layer of a kind in the table: 0 ground floor, 1 stages, 2 orchestrators, 3 the CLI.
fn rank(kind: &str) -> Option<u8> {
    match kind {
        "format" | "library" => Some(0),
        "stage" => Some(1),
        "orchestrator" => Some(2),
        "cli" => Some(3),
        _ => None,
    }
}

struct Row {
    kind: String,
    depends: String,
}

/// The module table of ARCHITECTURE.md: `| modules | kind | role | depends on |`, modules in
/// backticks (several per row allowed).
fn table() -> BTreeMap<String, Row> {
    let text = std::fs::read_to_string(root().join("ARCHITECTURE.md")).unwrap();
    let start = text
        .find("## Modules")
        .expect("ARCHITECTURE.md has a Modules section");
    let mut out = BTreeMap::new();
    for line in text[start..].lines().skip_while(|l| !l.starts_with('|')) {
        if !line.starts_with('|') {
            break;
        }
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() < 5 || cells[1] == "module" || cells[1].starts_with("---") {
            continue;
        }
        for m in cells[1].split('`').skip(1).step_by(2) {
            let prev = out.insert(
                m.to_string(),
                Row {
                    kind: cells[2].to_string(),
                    depends: cells[4].to_string(),
                },
            );
            assert!(prev.is_none(), "ARCHITECTURE.md lists `{m}` twice");
        }
    }
    out
}

/// The `pub mod` names of `src/lib.rs`.
fn modules() -> BTreeSet<String> {
    let lib = std::fs::read_to_string(root().join("src/lib.rs")).unwrap();
    lib.lines()
        .filter_map(|l| l.trim().strip_prefix("pub mod "))
        .map(|m| m.trim_end_matches(';').to_string())
        .collect()
}

fn rs_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rs_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// Source text without comments (line comments, doc comments and block comments) and without
/// the contents of string literals.
fn code_only(text: &str) -> String {
    split_source(text).0
}

/// The comments of a source text (line, doc and block comments), everything else dropped but
/// its line breaks, so that a line of the result is the same line of the source.
fn comments_only(text: &str) -> String {
    split_source(text).1
}

/// A source text split into its code (comments removed, string literals emptied) and its
/// comments (see [`comments_only`]).
fn split_source(text: &str) -> (String, String) {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut comments = String::new();
    let mut i = 0;
    // The line breaks of a skipped stretch, kept in the comments' text.
    let breaks = |s: &[u8], comments: &mut String| {
        comments.extend(s.iter().filter(|&&c| c == b'\n').map(|_| '\n'));
    };
    while i < b.len() {
        if b[i..].starts_with(b"//") {
            let start = i;
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
            comments.push_str(&text[start..i]);
        } else if b[i..].starts_with(b"/*") {
            let start = i;
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
            comments.push_str(&text[start..i.min(b.len())]);
        } else if let Some(hashes) = raw_string_start(b, i) {
            // A raw string `r#…#"…"#…#`: skip to the quote followed by as many `#`.
            let start = i;
            i += 2 + hashes;
            let close: Vec<u8> = std::iter::once(b'"')
                .chain(std::iter::repeat_n(b'#', hashes))
                .collect();
            while i < b.len() && !b[i..].starts_with(&close) {
                i += 1;
            }
            out.push_str("\"\"");
            i += close.len();
            breaks(&b[start..i.min(b.len())], &mut comments);
        } else if b[i] == b'"' && (i == 0 || b[i - 1] != b'\'') {
            // A string literal.
            let start = i;
            out.push('"');
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            out.push('"');
            i += 1;
            breaks(&b[start..i.min(b.len())], &mut comments);
        } else {
            let c = text[i..].chars().next().unwrap();
            out.push(c);
            if c == '\n' {
                comments.push('\n');
            }
            i += c.len_utf8();
        }
    }
    (out, comments)
}

/// At `i`, the number of `#` of a raw string's opening `r#…#"` (none when there is none).
fn raw_string_start(b: &[u8], i: usize) -> Option<usize> {
    let ident = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    if b[i] != b'r' || (i > 0 && ident(b[i - 1])) {
        return None;
    }
    let hashes = b[i + 1..].iter().take_while(|&&c| c == b'#').count();
    (b.get(i + 1 + hashes) == Some(&b'"')).then_some(hashes)
}

/// The top-level modules a piece of code names through `crate::` — in paths and in grouped
/// imports (`use crate::{a::x, b}` names `a` and `b`).
fn imports(code: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let ident = |s: &str| -> String {
        s.chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let mut rest = code;
    while let Some(k) = rest.find("crate::") {
        let before = rest[..k].chars().last();
        rest = &rest[k + "crate::".len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
            continue;
        }
        if let Some(group) = rest.strip_prefix('{') {
            // Top-level names of the group: after `{` or a comma at depth 1.
            let (mut depth, mut start) = (1, true);
            for (j, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => {
                        depth -= 1;
                        if depth == 0 {
                            break;
                        }
                    }
                    ',' if depth == 1 => start = true,
                    c if c.is_whitespace() => {}
                    _ => {
                        if start && depth == 1 {
                            let name = ident(&group[j..]);
                            if !name.is_empty() && name != "self" {
                                out.insert(name);
                            }
                        }
                        start = false;
                    }
                }
            }
        } else {
            let name = ident(rest);
            if !name.is_empty() {
                out.insert(name);
            }
        }
    }
    out
}

/// module → the other top-level modules it imports.
fn graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = root().join("src");
    let mut files = Vec::new();
    rs_files(&src, &mut files);
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in files {
        let rel = f.strip_prefix(&src).unwrap();
        let top = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if top == "lib" || top == "main" {
            continue;
        }
        let code = code_only(&std::fs::read_to_string(&f).unwrap());
        let e = g.entry(top.clone()).or_default();
        e.extend(imports(&code).into_iter().filter(|m| *m != top));
    }
    g
}

#[test]
fn every_module_is_in_the_table_with_a_known_kind() {
    let (t, m) = (table(), modules());
    let listed: BTreeSet<String> = t.keys().cloned().collect();
    assert_eq!(
        listed, m,
        "ARCHITECTURE.md's module table and src/lib.rs disagree"
    );
    for (name, row) in &t {
        assert!(
            rank(&row.kind).is_some(),
            "`{name}`: unknown kind `{}` (format, library, stage, orchestrator, cli)",
            row.kind
        );
    }
}

#[test]
fn imports_obey_the_layers_and_form_no_circle() {
    let (t, g) = (table(), graph());
    let kind = |m: &str| {
        t.get(m)
            .unwrap_or_else(|| panic!("`{m}` is not in ARCHITECTURE.md"))
            .kind
            .clone()
    };
    let mut bad = Vec::new();
    for (a, deps) in &g {
        let ra = rank(&kind(a)).unwrap();
        for b in deps {
            let Some(row) = t.get(b) else {
                bad.push(format!("{a} → {b}: `{b}` is not a module of the table"));
                continue;
            };
            let rb = rank(&row.kind).unwrap();
            let ok = rb < ra || (ra == 0 && rb == 0);
            if !ok {
                bad.push(format!("{a} ({}) imports {b} ({})", kind(a), row.kind));
            }
        }
    }
    assert!(bad.is_empty(), "layering broken:\n{}", bad.join("\n"));
    // No circle: repeatedly remove modules that import nothing left.
    let mut left: BTreeMap<&String, BTreeSet<&String>> = g
        .iter()
        .map(|(a, d)| (a, d.iter().filter(|b| g.contains_key(*b)).collect()))
        .collect();
    loop {
        let leaves: Vec<&String> = left
            .iter()
            .filter(|(_, d)| d.is_empty())
            .map(|(a, _)| *a)
            .collect();
        if leaves.is_empty() {
            break;
        }
        for l in &leaves {
            left.remove(l);
        }
        for d in left.values_mut() {
            for l in &leaves {
                d.remove(l);
            }
        }
    }
    assert!(
        left.is_empty(),
        "import circle among: {:?}",
        left.keys().collect::<Vec<_>>()
    );
}

#[test]
fn the_table_names_every_import() {
    let (t, g) = (table(), graph());
    let mut missing = Vec::new();
    for (a, deps) in &g {
        let cell = &t[a].depends;
        if cell.contains("everything") {
            continue;
        }
        let named: BTreeSet<&str> = cell
            .split(|c: char| !(c.is_alphanumeric() || c == '_'))
            .filter(|w| !w.is_empty())
            .collect();
        for b in deps {
            let every_stage = cell.contains("every stage") && t[b].kind == "stage";
            if !named.contains(b.as_str()) && !every_stage {
                missing.push(format!("{a} imports {b}"));
            }
        }
    }
    assert!(
        missing.is_empty(),
        "ARCHITECTURE.md's \"depends on\" column misses:\n{}",
        missing.join("\n")
    );
}

#[test]
fn the_import_reader_sees_paths_groups_and_skips_comments() {
    let code = code_only(
        "use crate::a::X;\nuse crate::{b::{self, Y}, c, self};\n// crate::d\n/// crate::e\n\
         let s = \"crate::f\";\nfn g() { crate::h::run(); my_crate::i(); }\n/* crate::j */\n\
         let r = r#\"{\"k\": \"crate::k\"}\"#; let c = '\"'; crate::l::x();",
    );
    let got: Vec<String> = imports(&code).into_iter().collect();
    assert_eq!(got, ["a", "b", "c", "h", "l"]);
}

/// One word of history or of a machine in the product's text: its kind and the matched text.
#[derive(Debug, PartialEq)]
struct HistoryWord {
    line: usize,
    kind: &'static str,
    text: String,
}

const MONTHS: &str = "(?:Jan(?:uary)?|Feb(?:ruary)?|Mar(?:ch)?|Apr(?:il)?|May|June?|July?|\
                      Aug(?:ust)?|Sep(?:t(?:ember)?)?|Oct(?:ober)?|Nov(?:ember)?|Dec(?:ember)?)";

/// The patterns of history and machine words, each with its kind. A match counts unless the
/// character before it continues a word, a number or a path (`x2026-11-27`, `1.2026-11-27`,
/// `a/work/`); `date` matches that are a value of the text (after `=`, `<`, `>` or a quote:
/// `creationDate >= 2020-09-01`) are data, not history.
fn history_patterns() -> Vec<(&'static str, regex::Regex)> {
    let re = |s: &str| regex::Regex::new(s).unwrap();
    vec![
        // 2026-11-27, 2026/11/27, 27.11.2026, 11/27/2026, 27 Nov 2026, November 27, 2026, Nov 2026.
        (
            "date",
            re(&[
                r"\b(?:19|20)\d\d[-/](?:0[1-9]|1[0-2])[-/](?:0[1-9]|[12]\d|3[01])\b",
                r"\b\d{1,2}[./]\d{1,2}[./](?:19|20)\d\d\b",
                &format!(r"\b\d{{1,2}}\s+{MONTHS}\.?\s+(?:19|20)\d\d\b"),
                &format!(r"\b{MONTHS}\.?\s+(?:\d{{1,2}},?\s+)?(?:19|20)\d\d\b"),
            ]
            .join("|")),
        ),
        ("session", re(r"(?i)\bsessions?\s+(?:no\.?\s*)?#?\d+")),
        // "issue 23", "issues 13 and 14", "PR #4", "#23" (not `owner/repo#23`, `&#23;`, `#[…]`).
        (
            "issue",
            re(r"(?i)\b(?:issues?|PRs?|pull\s+requests?|tickets?)\s+(?:no\.?\s*)?#?\d+|#\d+\b"),
        ),
        ("wave", re(r"(?i)\bwaves?\s+\d+")),
        // Absolute paths of a machine's own folders (not system paths such as /usr/include).
        (
            "path",
            re(r"/(?:work|home|root|Users|mnt|scratch|media)/|\b[A-Za-z]:\\(?:Users|work)\\"),
        ),
    ]
}

/// The history and machine words of a text, by line (1-based).
fn history_words(text: &str) -> Vec<HistoryWord> {
    let patterns = history_patterns();
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        for (kind, re) in &patterns {
            for m in re.find_iter(line) {
                let before = line[..m.start()].chars().next_back();
                let continues = |c: char| c.is_alphanumeric() || "_-.~/&".contains(c);
                if *kind == "path" && m.as_str().starts_with('/') && before.is_some_and(continues) {
                    continue;
                }
                if *kind == "issue"
                    && m.as_str().starts_with('#')
                    && before.is_some_and(|c| continues(c) || c == '#')
                {
                    continue;
                }
                if *kind == "date" {
                    let value = line[..m.start()].trim_end().chars().next_back();
                    if before.is_some_and(continues) || value.is_some_and(|c| "=<>\"'".contains(c))
                    {
                        continue;
                    }
                }
                out.push(HistoryWord {
                    line: n + 1,
                    kind,
                    text: m.as_str().to_string(),
                });
            }
        }
    }
    out
}

/// The product's words: README.md, BENCHMARKS.md, ARCHITECTURE.md, docs/**/*.md and the
/// comments of src/**/*.rs, each with its path. (CHANGELOG.md keeps the history.)
fn product_texts() -> Vec<(PathBuf, String)> {
    fn md_files(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                md_files(&p, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    let mut files: Vec<PathBuf> = ["README.md", "BENCHMARKS.md", "ARCHITECTURE.md"]
        .iter()
        .map(|f| root().join(f))
        .collect();
    md_files(&root().join("docs"), &mut files);
    let mut out: Vec<(PathBuf, String)> = files
        .into_iter()
        .map(|f| {
            let text = std::fs::read_to_string(&f).unwrap();
            (f, text)
        })
        .collect();
    let mut rs = Vec::new();
    rs_files(&root().join("src"), &mut rs);
    for f in rs {
        let text = comments_only(&std::fs::read_to_string(&f).unwrap());
        out.push((f, text));
    }
    out
}

#[test]
fn the_products_words_carry_no_history_and_no_machine() {
    let mut found = Vec::new();
    for (path, text) in product_texts() {
        let rel = path.strip_prefix(root()).unwrap().display().to_string();
        for w in history_words(&text) {
            found.push(format!("{rel}:{}: {} `{}`", w.line, w.kind, w.text));
        }
    }
    assert!(
        found.is_empty(),
        "the product's words describe the product as it is now: no dates, sessions, issue \
         numbers, waves or machine paths (history belongs in git and CHANGELOG.md):\n{}",
        found.join("\n")
    );
}

/// README.md is a guide (≤ 200 lines) and BENCHMARKS.md holds current figures (≤ 400 lines):
/// per-command detail belongs in `--help` and docs/, older measurements in git.
#[test]
fn the_readme_and_the_benchmarks_stay_short() {
    for (file, max) in [("README.md", 200), ("BENCHMARKS.md", 400)] {
        let n = std::fs::read_to_string(root().join(file))
            .unwrap()
            .lines()
            .count();
        assert!(n <= max, "{file} has {n} lines, at most {max}");
    }
}

#[test]
fn the_history_reader_finds_dates_sessions_issues_waves_and_paths_and_nothing_else() {
    let kinds =
        |t: &str| -> Vec<&'static str> { history_words(t).iter().map(|w| w.kind).collect() };
    // Each of these is found, with its kind.
    for (text, kind) in [
        ("re-measured 2026-11-27 with the prior", "date"),
        ("(measured 2026/11/27)", "date"),
        ("on 27.11.2026 at load 3", "date"),
        ("on 27 Nov 2026 at load 3", "date"),
        ("since November 27, 2026", "date"),
        ("as of March 2025", "date"),
        ("in session 9 we", "date-less session"),
        ("fixed in issue 23", "issue"),
        ("Issues 13 and 14", "issue"),
        ("see #23 for why", "issue"),
        ("(PR #4)", "issue"),
        ("the Wave 2 contract", "wave"),
        ("`/work/runs/street_core`", "path"),
        ("cd /home/dev/gs4city", "path"),
        ("C:\\Users\\dev\\gs4city", "path"),
    ] {
        let kind = if kind == "date-less session" {
            "session"
        } else {
            kind
        };
        assert_eq!(kinds(text), [kind], "{text}");
    }
    // None of these is history: codes, versions, data values, attributes, external references.
    for text in [
        "EPSG:25832 and EPSG:4979",
        "gs4city 0.1.0, CesiumJS 1.145, PROJ 9.1.1, Embree 3.13.5",
        "#[derive(Debug)] and #![deny(unsafe_code)]",
        "creationDate >= 2020-09-01 and creationDate=\"2020-06-24\"",
        "`creationDate<'2020-09-01'`",
        "RenderKit/embree#207 (an external repository's issue)",
        "github.com/facebookresearch/segment-anything/issues/56",
        "&#8212; and `masks/Ansicht-ü#1.png`",
        "../shared/data/citygml and /usr/include/embree3 and S/work/x",
        "a wave of 3 views; 2 sessions of ONNX Runtime",
        "1 200 000 Gaussians, 128 views of 660×494, 16.32 s",
        "https://github.com/home/repo",
    ] {
        assert_eq!(kinds(text), Vec::<&str>::new(), "{text}");
    }
}

#[test]
fn the_comment_reader_keeps_lines_and_skips_code_and_strings() {
    let text = "let a = \"// not a comment\";\n/// doc 2026-11-27\nlet b = 1; // tail\n\
                let s = r#\"/* no */\"#;\n/* block\n over */ let c = '\"'; // after\n";
    let c = comments_only(text);
    let lines: Vec<&str> = c.lines().collect();
    assert_eq!(
        lines,
        [
            "",
            "/// doc 2026-11-27",
            "// tail",
            "",
            "/* block",
            " over */// after"
        ]
    );
    assert_eq!(history_words(&c)[0].line, 2);
}
