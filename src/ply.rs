//! The PLY format (a reader/writer: depends on no pipeline stage): header parsing, element
//! reading in ASCII and binary little/big-endian, and writing. [`crate::splat`] (3DGS
//! Gaussians) and [`crate::mesh`] (the labelled city mesh) are layouts on top of it.
//!
//! ## Reading
//! [`Reader::new`] parses and checks the header, then [`Reader::read_element`] hands the
//! rows of one element to a callback as a [`Row`] (every scalar as `f64`, which holds every
//! PLY scalar type exactly; lists as slices). Elements are read in file order; the ones a
//! caller does not ask for are skipped. [`Reader::finish`] checks that nothing follows the
//! last element.
//!
//! ## What is checked, before anything is allocated
//! * The header: `ply`, one `format` line (`ascii`, `binary_little_endian`,
//!   `binary_big_endian`, version 1.0), `element NAME COUNT` / `property TYPE NAME` /
//!   `property list COUNT_TYPE ITEM_TYPE NAME` lines with known types, unique element and
//!   property names, an integer list count type, `end_header` within the first
//!   [`MAX_HEADER_BYTES`]. An element with rows but no properties is refused (it would be
//!   read as an endless run of empty rows).
//! * Sizes: for every element the smallest possible payload (`COUNT` × the smallest row: all
//!   scalars plus the list counts in binary, two bytes per value in ASCII) is computed with
//!   checked arithmetic and compared with the bytes after the header, so a header that
//!   promises 10¹² rows fails at once instead of allocating.
//! * The payload: truncation (naming the element, row and, in ASCII, line), ASCII tokens
//!   that do not parse as their type or do not fit it (`uchar 300`), list counts below zero
//!   or beyond the file, rows with too few or too many ASCII values, and data after the last
//!   element ("more data than the header declares").
//!
//! Every error names the file and, where one is at fault, the element, the row and the line.
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::fsutil::FsError;

/// The longest header accepted (bytes up to and including `end_header`).
pub const MAX_HEADER_BYTES: usize = 1 << 20;

/// Errors of PLY reading and writing; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error("cannot read {path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    #[error("{path}: PLY header line {line}: {why}")]
    Header {
        path: PathBuf,
        line: usize,
        why: String,
    },
    #[error("{path}: {why}")]
    Size { path: PathBuf, why: String },
    #[error("{path}: the file ends in {element} {row} of {count}{}", at_line(*line))]
    Truncated {
        path: PathBuf,
        element: String,
        row: usize,
        count: usize,
        line: Option<usize>,
    },
    #[error("{path}: {element} {row}{}: {why}", at_line(*line))]
    Row {
        path: PathBuf,
        element: String,
        row: usize,
        line: Option<usize>,
        why: String,
    },
    #[error("{path}: {why}")]
    Trailing { path: PathBuf, why: String },
    #[error("{path}: {why}")]
    Layout { path: PathBuf, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// ` (line N)` for ASCII rows, nothing for binary ones.
pub fn at_line(line: Option<usize>) -> String {
    line.map(|l| format!(" (line {l})")).unwrap_or_default()
}

/// PLY payload encodings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

impl Encoding {
    /// The header's `format` keyword.
    pub fn keyword(self) -> &'static str {
        match self {
            Encoding::Ascii => "ascii",
            Encoding::BinaryLittleEndian => "binary_little_endian",
            Encoding::BinaryBigEndian => "binary_big_endian",
        }
    }
}

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum ScalarKind {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarKind {
    /// Bytes per value in a binary PLY.
    pub fn size(self) -> usize {
        match self {
            ScalarKind::I8 | ScalarKind::U8 => 1,
            ScalarKind::I16 | ScalarKind::U16 => 2,
            ScalarKind::I32 | ScalarKind::U32 | ScalarKind::F32 => 4,
            ScalarKind::F64 => 8,
        }
    }

    /// The PLY header type name.
    pub fn ply_name(self) -> &'static str {
        match self {
            ScalarKind::I8 => "char",
            ScalarKind::U8 => "uchar",
            ScalarKind::I16 => "short",
            ScalarKind::U16 => "ushort",
            ScalarKind::I32 => "int",
            ScalarKind::U32 => "uint",
            ScalarKind::F32 => "float",
            ScalarKind::F64 => "double",
        }
    }

    /// The type named `name` (the classic names and the sized aliases `int8` … `float64`).
    pub fn from_ply_name(name: &str) -> Option<ScalarKind> {
        Some(match name {
            "char" | "int8" => ScalarKind::I8,
            "uchar" | "uint8" => ScalarKind::U8,
            "short" | "int16" => ScalarKind::I16,
            "ushort" | "uint16" => ScalarKind::U16,
            "int" | "int32" => ScalarKind::I32,
            "uint" | "uint32" => ScalarKind::U32,
            "float" | "float32" => ScalarKind::F32,
            "double" | "float64" => ScalarKind::F64,
            _ => return None,
        })
    }

    /// Whether the type is a float type.
    pub fn is_float(self) -> bool {
        matches!(self, ScalarKind::F32 | ScalarKind::F64)
    }

    /// The range of an integer type (`None` for floats).
    fn int_range(self) -> Option<(i64, i64)> {
        Some(match self {
            ScalarKind::I8 => (i8::MIN.into(), i8::MAX.into()),
            ScalarKind::U8 => (0, u8::MAX.into()),
            ScalarKind::I16 => (i16::MIN.into(), i16::MAX.into()),
            ScalarKind::U16 => (0, u16::MAX.into()),
            ScalarKind::I32 => (i32::MIN.into(), i32::MAX.into()),
            ScalarKind::U32 => (0, u32::MAX.into()),
            ScalarKind::F32 | ScalarKind::F64 => return None,
        })
    }

    /// Decodes one value from exactly [`ScalarKind::size`] bytes.
    #[inline]
    pub fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:literal) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }
            }};
        }
        match self {
            ScalarKind::I8 => f64::from(b[0] as i8),
            ScalarKind::U8 => f64::from(b[0]),
            ScalarKind::I16 => f64::from(get!(i16, 2)),
            ScalarKind::U16 => f64::from(get!(u16, 2)),
            ScalarKind::I32 => f64::from(get!(i32, 4)),
            ScalarKind::U32 => f64::from(get!(u32, 4)),
            ScalarKind::F32 => f64::from(get!(f32, 4)),
            ScalarKind::F64 => get!(f64, 8),
        }
    }

    /// Parses one ASCII token; `None` when it is not a value of this type. Floats accept
    /// `nan`/`inf` (callers decide about them); integers must fit the type.
    pub fn parse(self, tok: &str) -> Option<f64> {
        match self {
            ScalarKind::F32 => tok.parse::<f32>().ok().map(f64::from),
            ScalarKind::F64 => tok.parse::<f64>().ok(),
            _ => {
                let v = tok.parse::<i64>().ok()?;
                let (lo, hi) = self.int_range()?;
                (lo..=hi).contains(&v).then_some(v as f64)
            }
        }
    }

    /// Appends the binary encoding of `v` (converted with Rust's `as`, i.e. saturating for
    /// integers; callers store values that fit).
    #[inline]
    pub fn encode(self, v: f64, big_endian: bool, out: &mut Vec<u8>) {
        macro_rules! put {
            ($x:expr) => {
                if big_endian {
                    out.extend_from_slice(&$x.to_be_bytes())
                } else {
                    out.extend_from_slice(&$x.to_le_bytes())
                }
            };
        }
        match self {
            ScalarKind::I8 => put!(v as i8),
            ScalarKind::U8 => put!(v as u8),
            ScalarKind::I16 => put!(v as i16),
            ScalarKind::U16 => put!(v as u16),
            ScalarKind::I32 => put!(v as i32),
            ScalarKind::U32 => put!(v as u32),
            ScalarKind::F32 => put!(v as f32),
            ScalarKind::F64 => put!(v),
        }
    }

    /// Appends the ASCII form of `v`: the shortest text that parses back to the same value
    /// for floats, the integer for integer types.
    pub fn format(self, v: f64, out: &mut String) {
        use std::fmt::Write as _;
        let _ = match self {
            ScalarKind::F32 => write!(out, "{:?}", v as f32),
            ScalarKind::F64 => write!(out, "{v:?}"),
            _ => write!(out, "{}", v as i64),
        };
    }
}

/// A property's type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PropertyKind {
    Scalar(ScalarKind),
    /// `property list COUNT ITEM name`.
    List {
        count: ScalarKind,
        item: ScalarKind,
    },
}

/// One `property` line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PropertyDef {
    pub name: String,
    pub kind: PropertyKind,
}

impl PropertyDef {
    /// A scalar property.
    pub fn scalar(name: impl Into<String>, kind: ScalarKind) -> PropertyDef {
        PropertyDef {
            name: name.into(),
            kind: PropertyKind::Scalar(kind),
        }
    }

    /// A list property.
    pub fn list(name: impl Into<String>, count: ScalarKind, item: ScalarKind) -> PropertyDef {
        PropertyDef {
            name: name.into(),
            kind: PropertyKind::List { count, item },
        }
    }
}

/// One `element` with its properties.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ElementDef {
    pub name: String,
    pub count: usize,
    pub properties: Vec<PropertyDef>,
}

impl ElementDef {
    /// Index of the property called `name`.
    pub fn property(&self, name: &str) -> Option<usize> {
        self.properties.iter().position(|p| p.name == name)
    }

    /// Bytes per row when every property is a scalar.
    pub fn fixed_stride(&self) -> Option<usize> {
        self.properties
            .iter()
            .map(|p| match p.kind {
                PropertyKind::Scalar(k) => Some(k.size()),
                PropertyKind::List { .. } => None,
            })
            .sum()
    }

    /// The fewest payload bytes one row can take in `encoding`.
    fn min_row_bytes(&self, encoding: Encoding) -> usize {
        match encoding {
            // Every value (and list count) is at least one character plus a separator.
            Encoding::Ascii => 2 * self.properties.len(),
            _ => self
                .properties
                .iter()
                .map(|p| match p.kind {
                    PropertyKind::Scalar(k) => k.size(),
                    PropertyKind::List { count, .. } => count.size(),
                })
                .sum(),
        }
    }
}

/// A parsed header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    pub encoding: Encoding,
    pub elements: Vec<ElementDef>,
    pub comments: Vec<String>,
    /// Bytes up to and including the `end_header` line.
    pub len: usize,
    /// Lines in the header (the first payload line of an ASCII file is `lines + 1`).
    pub lines: usize,
}

impl Header {
    /// Index of the element called `name`.
    pub fn element(&self, name: &str) -> Option<usize> {
        self.elements.iter().position(|e| e.name == name)
    }

    /// Parses the header at the start of `bytes` and checks the declared sizes against the
    /// payload that follows (module docs).
    pub fn parse(path: &Path, bytes: &[u8]) -> Result<Header, PlyError> {
        Header::parse_sized(path, bytes, bytes.len() as u64)
    }

    /// [`Header::parse`] of the first bytes `head` of a file of `file_len` bytes (the whole
    /// file need not be in memory: `head` must hold the header, e.g. its first
    /// [`MAX_HEADER_BYTES`]); the declared sizes are checked against `file_len`.
    pub fn parse_sized(path: &Path, bytes: &[u8], file_len: u64) -> Result<Header, PlyError> {
        let err = |line: usize, why: String| PlyError::Header {
            path: path.to_path_buf(),
            line,
            why,
        };
        let mut pos = 0usize;
        let mut line_no = 0usize;
        let mut encoding = None;
        let mut elements: Vec<ElementDef> = Vec::new();
        let mut comments = Vec::new();
        loop {
            line_no += 1;
            let rest = &bytes[pos..];
            let Some(nl) = rest
                .iter()
                .take(MAX_HEADER_BYTES.saturating_sub(pos))
                .position(|&b| b == b'\n')
            else {
                return Err(if bytes.len() >= MAX_HEADER_BYTES {
                    err(
                        line_no,
                        format!("no end_header within the first {MAX_HEADER_BYTES} bytes"),
                    )
                } else if line_no == 1 {
                    err(1, "not a PLY file (the first line is not `ply`)".into())
                } else {
                    err(line_no, "the file ends before end_header".into())
                });
            };
            let raw = &rest[..nl];
            pos += nl + 1;
            let Ok(text) = std::str::from_utf8(raw) else {
                return Err(err(
                    line_no,
                    if line_no == 1 {
                        "not a PLY file (the first line is not `ply`)".into()
                    } else {
                        "the header is not text".into()
                    },
                ));
            };
            let text = text.strip_suffix('\r').unwrap_or(text);
            let mut words = text.split_ascii_whitespace();
            let keyword = words.next().unwrap_or("");
            if line_no == 1 {
                if text.trim() != "ply" {
                    return Err(err(
                        1,
                        "not a PLY file (the first line is not `ply`)".into(),
                    ));
                }
                continue;
            }
            match keyword {
                "format" => {
                    if encoding.is_some() {
                        return Err(err(line_no, "a second `format` line".into()));
                    }
                    let (Some(fmt), Some(version), None) =
                        (words.next(), words.next(), words.next())
                    else {
                        return Err(err(
                            line_no,
                            format!("`{text}` is not `format <encoding> 1.0`"),
                        ));
                    };
                    encoding = Some(match fmt {
                        "ascii" => Encoding::Ascii,
                        "binary_little_endian" => Encoding::BinaryLittleEndian,
                        "binary_big_endian" => Encoding::BinaryBigEndian,
                        _ => {
                            return Err(err(
                                line_no,
                                format!(
                                    "unknown format `{fmt}` (ascii, binary_little_endian or binary_big_endian)"
                                ),
                            ));
                        }
                    });
                    if version != "1.0" && version != "1" {
                        return Err(err(
                            line_no,
                            format!("PLY version {version} is not supported (1.0)"),
                        ));
                    }
                }
                "comment" | "obj_info" => {
                    comments.push(text[keyword.len()..].trim().to_string());
                }
                "element" => {
                    let (Some(name), Some(count), None) =
                        (words.next(), words.next(), words.next())
                    else {
                        return Err(err(
                            line_no,
                            format!("`{text}` is not `element <name> <count>`"),
                        ));
                    };
                    let count: usize = count.parse().map_err(|_| {
                        err(
                            line_no,
                            format!("element `{name}`: count `{count}` is not a whole number that fits in memory addresses"),
                        )
                    })?;
                    if elements.iter().any(|e| e.name == name) {
                        return Err(err(line_no, format!("element `{name}` is declared twice")));
                    }
                    elements.push(ElementDef {
                        name: name.to_string(),
                        count,
                        properties: Vec::new(),
                    });
                }
                "property" => {
                    let Some(element) = elements.last_mut() else {
                        return Err(err(line_no, "a property before any element".into()));
                    };
                    let toks: Vec<&str> = words.collect();
                    let ty = |t: &str| {
                        ScalarKind::from_ply_name(t)
                            .ok_or_else(|| err(line_no, format!("unknown property type `{t}`")))
                    };
                    let def = match toks.as_slice() {
                        ["list", c, i, name] => {
                            let count = ty(c)?;
                            if count.is_float() {
                                return Err(err(
                                    line_no,
                                    format!(
                                        "list `{name}`: the count type `{c}` is not an integer type"
                                    ),
                                ));
                            }
                            PropertyDef::list(*name, count, ty(i)?)
                        }
                        [t, name] if *t != "list" => PropertyDef::scalar(*name, ty(t)?),
                        _ => {
                            return Err(err(
                                line_no,
                                format!(
                                    "`{text}` is not `property <type> <name>` or `property list <count type> <item type> <name>`"
                                ),
                            ));
                        }
                    };
                    if element.property(&def.name).is_some() {
                        return Err(err(
                            line_no,
                            format!(
                                "element `{}` declares property `{}` twice",
                                element.name, def.name
                            ),
                        ));
                    }
                    element.properties.push(def);
                }
                "end_header" => break,
                "" => {}
                other => {
                    return Err(err(line_no, format!("unknown header keyword `{other}`")));
                }
            }
        }
        let Some(encoding) = encoding else {
            return Err(err(line_no, "no `format` line before end_header".into()));
        };
        let payload = u128::from(file_len).saturating_sub(pos as u128);
        let mut need: u128 = 0;
        for e in &elements {
            if e.count > 0 && e.properties.is_empty() {
                return Err(PlyError::Size {
                    path: path.to_path_buf(),
                    why: format!(
                        "element `{}` declares {} rows but no properties",
                        e.name, e.count
                    ),
                });
            }
            // u128: count < 2^64 and a row's minimum < 2^64, so the product cannot overflow.
            let before = need;
            need += e.count as u128 * e.min_row_bytes(encoding) as u128;
            let slack = u128::from(encoding == Encoding::Ascii); // the last newline may be missing
            if need > payload + slack {
                if let (Some(stride), false) = (e.fixed_stride(), encoding == Encoding::Ascii) {
                    // Exact row size: name the row where the data ends.
                    return Err(PlyError::Truncated {
                        path: path.to_path_buf(),
                        element: e.name.clone(),
                        row: ((payload - before) / stride as u128) as usize,
                        count: e.count,
                        line: None,
                    });
                }
                return Err(PlyError::Size {
                    path: path.to_path_buf(),
                    why: format!(
                        "the header declares {} `{}` rows, which need at least {need} bytes, but {payload} bytes follow the header (truncated file or wrong count)",
                        e.count, e.name
                    ),
                });
            }
        }
        Ok(Header {
            encoding,
            elements,
            comments,
            len: pos,
            lines: line_no,
        })
    }
}

/// One row of an element: every property's value (a list property's value is its length)
/// and the items of its lists.
#[derive(Debug, Clone, Default)]
pub struct Row {
    /// Row index within its element.
    pub index: usize,
    /// 1-based line of the row in an ASCII file.
    pub line: Option<usize>,
    values: Vec<f64>,
    lists: Vec<Vec<f64>>,
}

impl Row {
    /// The value of property `p` (header order).
    #[inline]
    pub fn get(&self, p: usize) -> f64 {
        self.values[p]
    }

    /// All values in header order.
    #[inline]
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// The items of list property `p` (empty for a scalar property).
    pub fn list(&self, p: usize) -> &[f64] {
        &self.lists[p]
    }
}

/// Reads the payload of a PLY file element by element (module docs).
pub struct Reader<'a> {
    path: &'a Path,
    header: Header,
    bytes: &'a [u8],
    pos: usize,
    /// Next element index to read.
    next: usize,
    /// Current line (ASCII).
    line: usize,
    generic: bool,
}

impl<'a> Reader<'a> {
    /// Parses the header of `bytes` (`path` names the file in errors).
    pub fn new(path: &'a Path, bytes: &'a [u8]) -> Result<Reader<'a>, PlyError> {
        let header = Header::parse(path, bytes)?;
        Ok(Reader {
            path,
            pos: header.len,
            line: header.lines,
            header,
            bytes,
            next: 0,
            generic: false,
        })
    }

    /// The parsed header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// Decodes every property one by one even where the all-`float` little-endian fast path
    /// applies (for benchmarks and for cross-checking the two).
    pub fn set_generic(&mut self, generic: bool) {
        self.generic = generic;
    }

    /// Whether element `e` would be decoded by the all-`float` little-endian fast path.
    pub fn fast_path(&self, e: usize) -> bool {
        !self.generic
            && self.header.encoding == Encoding::BinaryLittleEndian
            && self.header.elements[e]
                .properties
                .iter()
                .all(|p| p.kind == PropertyKind::Scalar(ScalarKind::F32))
    }

    fn row_err(&self, e: &ElementDef, row: usize, line: Option<usize>, why: String) -> PlyError {
        PlyError::Row {
            path: self.path.to_path_buf(),
            element: e.name.clone(),
            row,
            line,
            why,
        }
    }

    fn truncated(&self, e: &ElementDef, row: usize, line: Option<usize>) -> PlyError {
        PlyError::Truncated {
            path: self.path.to_path_buf(),
            element: e.name.clone(),
            row,
            count: e.count,
            line,
        }
    }

    /// Reads element `name`, skipping the elements before it, and calls `row` once per row
    /// in order. Fails when the element does not exist or was already passed.
    pub fn read_element<E: From<PlyError>>(
        &mut self,
        name: &str,
        mut row: impl FnMut(&Row) -> Result<(), E>,
    ) -> Result<(), E> {
        let Some(target) = self.header.element(name) else {
            return Err(PlyError::Layout {
                path: self.path.to_path_buf(),
                why: format!("no `{name}` element"),
            }
            .into());
        };
        if target < self.next {
            return Err(PlyError::Layout {
                path: self.path.to_path_buf(),
                why: format!("element `{name}` was already read"),
            }
            .into());
        }
        while self.next < target {
            self.skip_next()?;
        }
        self.next += 1;
        self.rows(target, &mut row)
    }

    fn skip_next(&mut self) -> Result<(), PlyError> {
        let e = self.next;
        self.next += 1;
        self.rows(e, &mut |_: &Row| Ok::<(), PlyError>(()))
    }

    /// Skips what is left and checks that no data follows the last element.
    pub fn finish(mut self) -> Result<(), PlyError> {
        while self.next < self.header.elements.len() {
            self.skip_next()?;
        }
        let rest = &self.bytes[self.pos..];
        let last = self
            .header
            .elements
            .last()
            .map(|e| format!("`{}`", e.name))
            .unwrap_or_else(|| "the header".into());
        match self.header.encoding {
            Encoding::Ascii => {
                let mut line = self.line;
                for l in rest.split(|&b| b == b'\n') {
                    line += 1;
                    if !l.iter().all(|b| b.is_ascii_whitespace()) {
                        return Err(PlyError::Trailing {
                            path: self.path.to_path_buf(),
                            why: format!(
                                "line {line}: data after the last row of {last}: the file holds more rows than its header declares"
                            ),
                        });
                    }
                }
            }
            _ if !rest.is_empty() => {
                return Err(PlyError::Trailing {
                    path: self.path.to_path_buf(),
                    why: format!(
                        "{} bytes after the last row of {last}: the file holds more data than its header declares",
                        rest.len()
                    ),
                });
            }
            _ => {}
        }
        Ok(())
    }

    fn rows<E: From<PlyError>>(
        &mut self,
        e: usize,
        f: &mut impl FnMut(&Row) -> Result<(), E>,
    ) -> Result<(), E> {
        let def = self.header.elements[e].clone();
        let mut row = Row {
            index: 0,
            line: None,
            values: vec![0.0; def.properties.len()],
            lists: vec![Vec::new(); def.properties.len()],
        };
        match self.header.encoding {
            Encoding::Ascii => self.ascii_rows(&def, &mut row, f),
            enc => {
                let big = enc == Encoding::BinaryBigEndian;
                match def.fixed_stride() {
                    Some(stride) => self.fixed_rows(e, &def, stride, big, &mut row, f),
                    None => self.list_rows(&def, big, &mut row, f),
                }
            }
        }
    }

    /// Binary rows of scalars only: fixed stride, one bounds check for the whole element.
    fn fixed_rows<E: From<PlyError>>(
        &mut self,
        e: usize,
        def: &ElementDef,
        stride: usize,
        big: bool,
        row: &mut Row,
        f: &mut impl FnMut(&Row) -> Result<(), E>,
    ) -> Result<(), E> {
        let avail = self.bytes.len() - self.pos;
        let total = def.count.checked_mul(stride).filter(|&t| t <= avail);
        let Some(total) = total else {
            return Err(self.truncated(def, avail / stride.max(1), None).into());
        };
        let data = &self.bytes[self.pos..self.pos + total];
        self.pos += total;
        if stride == 0 {
            return Ok(());
        }
        if self.fast_path(e) {
            for (i, chunk) in data.chunks_exact(stride).enumerate() {
                for (v, b) in row.values.iter_mut().zip(chunk.chunks_exact(4)) {
                    *v = f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                }
                row.index = i;
                f(row)?;
            }
        } else {
            let layout: Vec<(usize, ScalarKind)> = def
                .properties
                .iter()
                .scan(0usize, |off, p| {
                    let PropertyKind::Scalar(k) = p.kind else {
                        unreachable!("fixed_stride() is Some only for scalar rows")
                    };
                    let o = *off;
                    *off += k.size();
                    Some((o, k))
                })
                .collect();
            for (i, chunk) in data.chunks_exact(stride).enumerate() {
                for (v, &(o, k)) in row.values.iter_mut().zip(&layout) {
                    *v = k.decode(&chunk[o..], big);
                }
                row.index = i;
                f(row)?;
            }
        }
        Ok(())
    }

    /// Binary rows with lists: bounds checked per value.
    fn list_rows<E: From<PlyError>>(
        &mut self,
        def: &ElementDef,
        big: bool,
        row: &mut Row,
        f: &mut impl FnMut(&Row) -> Result<(), E>,
    ) -> Result<(), E> {
        for i in 0..def.count {
            row.index = i;
            for (p, prop) in def.properties.iter().enumerate() {
                match prop.kind {
                    PropertyKind::Scalar(k) => {
                        let b = self
                            .take(k.size())
                            .ok_or_else(|| self.truncated(def, i, None))?;
                        row.values[p] = k.decode(b, big);
                    }
                    PropertyKind::List { count, item } => {
                        let b = self
                            .take(count.size())
                            .ok_or_else(|| self.truncated(def, i, None))?;
                        let n = count.decode(b, big);
                        if n < 0.0 {
                            return Err(self
                                .row_err(
                                    def,
                                    i,
                                    None,
                                    format!("list `{}` has {n} items", prop.name),
                                )
                                .into());
                        }
                        let n = n as usize;
                        let avail = (self.bytes.len() - self.pos) / item.size();
                        if n > avail {
                            return Err(self.truncated(def, i, None).into());
                        }
                        let b = self.take(n * item.size()).expect("checked above");
                        row.values[p] = n as f64;
                        let list = &mut row.lists[p];
                        list.clear();
                        list.extend(b.chunks_exact(item.size()).map(|c| item.decode(c, big)));
                    }
                }
            }
            f(row)?;
        }
        Ok(())
    }

    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let b = self.bytes.get(self.pos..self.pos.checked_add(n)?)?;
        self.pos += n;
        Some(b)
    }

    /// ASCII rows: one row per line (blank lines are skipped), whitespace-separated values.
    fn ascii_rows<E: From<PlyError>>(
        &mut self,
        def: &ElementDef,
        row: &mut Row,
        f: &mut impl FnMut(&Row) -> Result<(), E>,
    ) -> Result<(), E> {
        for i in 0..def.count {
            // Next non-blank line.
            let text = loop {
                if self.pos >= self.bytes.len() {
                    return Err(self.truncated(def, i, Some(self.line + 1)).into());
                }
                let rest = &self.bytes[self.pos..];
                let n = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
                let raw = &rest[..n];
                self.pos += (n + 1).min(rest.len());
                self.line += 1;
                if !raw.iter().all(|b| b.is_ascii_whitespace()) {
                    break raw;
                }
            };
            let line = Some(self.line);
            let text = std::str::from_utf8(text)
                .map_err(|_| self.row_err(def, i, line, "the line is not text".into()))?;
            let mut toks = text.split_ascii_whitespace();
            let mut next = |what: &dyn Fn() -> String| {
                toks.next()
                    .ok_or_else(|| self.row_err(def, i, line, format!("no value for {}", what())))
            };
            for (p, prop) in def.properties.iter().enumerate() {
                let parse = |k: ScalarKind, tok: &str, what: &dyn Fn() -> String| {
                    k.parse(tok).ok_or_else(|| {
                        self.row_err(
                            def,
                            i,
                            line,
                            format!("`{tok}` is not a {} ({})", k.ply_name(), what()),
                        )
                    })
                };
                match prop.kind {
                    PropertyKind::Scalar(k) => {
                        let what = || format!("`{}`", prop.name);
                        let tok = next(&what)?;
                        row.values[p] = parse(k, tok, &what)?;
                    }
                    PropertyKind::List { count, item } => {
                        let what = || format!("the length of list `{}`", prop.name);
                        let tok = next(&what)?;
                        let n = parse(count, tok, &what)?;
                        if n < 0.0 {
                            return Err(self
                                .row_err(
                                    def,
                                    i,
                                    line,
                                    format!("list `{}` has {n} items", prop.name),
                                )
                                .into());
                        }
                        row.values[p] = n;
                        row.lists[p].clear();
                        for k in 0..n as usize {
                            let what = || format!("item {k} of list `{}`", prop.name);
                            let tok = next(&what)?;
                            let v = parse(item, tok, &what)?;
                            row.lists[p].push(v);
                        }
                    }
                }
            }
            if toks.next().is_some() {
                return Err(self
                    .row_err(
                        def,
                        i,
                        line,
                        format!(
                            "more values than the {} properties of `{}`",
                            def.properties.len(),
                            def.name
                        ),
                    )
                    .into());
            }
            row.index = i;
            row.line = line;
            f(row)?;
        }
        row.line = None;
        Ok(())
    }
}

/// The header text for `elements` (counts included) in `encoding`.
pub fn header_text(encoding: Encoding, comments: &[&str], elements: &[ElementDef]) -> String {
    let mut h = format!("ply\nformat {} 1.0\n", encoding.keyword());
    for c in comments {
        h.push_str(&format!("comment {c}\n"));
    }
    for e in elements {
        h.push_str(&format!("element {} {}\n", e.name, e.count));
        for p in &e.properties {
            match p.kind {
                PropertyKind::Scalar(k) => {
                    h.push_str(&format!("property {} {}\n", k.ply_name(), p.name))
                }
                PropertyKind::List { count, item } => h.push_str(&format!(
                    "property list {} {} {}\n",
                    count.ply_name(),
                    item.ply_name(),
                    p.name
                )),
            }
        }
    }
    h.push_str("end_header\n");
    h
}

/// Encodes rows into a byte buffer (the caller writes it out when [`RowWriter::len`] grows).
pub struct RowWriter {
    encoding: Encoding,
    buf: Vec<u8>,
    /// Whether the current ASCII row has a value yet.
    started: bool,
    text: String,
}

impl RowWriter {
    /// A writer whose buffer starts with the header for `elements`.
    pub fn new(encoding: Encoding, comments: &[&str], elements: &[ElementDef]) -> RowWriter {
        let head = header_text(encoding, comments, elements);
        let mut buf = Vec::with_capacity(1 << 17);
        buf.extend_from_slice(head.as_bytes());
        RowWriter {
            encoding,
            buf,
            started: false,
            text: String::new(),
        }
    }

    /// Appends one scalar value.
    #[inline]
    pub fn scalar(&mut self, kind: ScalarKind, v: f64) {
        match self.encoding {
            Encoding::Ascii => {
                if self.started {
                    self.buf.push(b' ');
                }
                self.started = true;
                self.text.clear();
                kind.format(v, &mut self.text);
                self.buf.extend_from_slice(self.text.as_bytes());
            }
            Encoding::BinaryLittleEndian => kind.encode(v, false, &mut self.buf),
            Encoding::BinaryBigEndian => kind.encode(v, true, &mut self.buf),
        }
    }

    /// Appends one list value: its length, then its items.
    pub fn list(&mut self, count: ScalarKind, item: ScalarKind, items: &[f64]) {
        self.scalar(count, items.len() as f64);
        for &v in items {
            self.scalar(item, v);
        }
    }

    /// Ends a row (the newline of an ASCII row).
    #[inline]
    pub fn end_row(&mut self) {
        if self.encoding == Encoding::Ascii {
            self.buf.push(b'\n');
            self.started = false;
        }
    }

    /// Bytes buffered.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether nothing is buffered.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Writes the buffer to `w` and empties it.
    pub fn drain_to(&mut self, w: &mut impl Write) -> std::io::Result<()> {
        w.write_all(&self.buf)?;
        self.buf.clear();
        Ok(())
    }

    /// The buffered bytes (for in-memory encoding).
    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }
}

/// Reads and checks the header of the file at `path` only (its declared sizes against the
/// file's size), without reading the payload; returns it with the file's size.
pub fn read_header(path: &Path) -> Result<(Header, u64), PlyError> {
    let io = |err| PlyError::Io {
        path: path.to_path_buf(),
        err,
    };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let file_len = f.metadata().map_err(io)?.len();
    let mut head = vec![0u8; (file_len.min(MAX_HEADER_BYTES as u64)) as usize];
    std::io::Read::read_exact(&mut f, &mut head).map_err(io)?;
    Ok((Header::parse_sized(path, &head, file_len)?, file_len))
}

/// The rows of one element of a binary PLY whose elements all have fixed-size rows, read from
/// the file in chunks: memory independent of the file size (`gs4city tile` cuts a city's PLY
/// this way). The header is checked against the file's size first, and the file must hold
/// exactly the bytes the header declares.
#[derive(Debug, Clone)]
pub struct FixedRows {
    pub path: PathBuf,
    pub header: Header,
    /// Index of the streamed element in [`Header::elements`].
    pub element: usize,
    /// Byte offset of the element's first row in the file.
    pub start: u64,
    /// Bytes per row.
    pub stride: usize,
    /// Byte offset of each property within a row (header order).
    pub offsets: Vec<usize>,
}

impl FixedRows {
    /// Opens `path` and finds element `name` (errors name the file).
    pub fn open(path: &Path, name: &str) -> Result<FixedRows, PlyError> {
        let layout = |why: String| PlyError::Layout {
            path: path.to_path_buf(),
            why,
        };
        let (header, file_len) = read_header(path)?;
        if header.encoding == Encoding::Ascii {
            return Err(layout(
                "an ASCII PLY cannot be read in chunks; convert it to binary (e.g. `gs4city render` \
                 reads it, any PLY tool writes binary_little_endian)"
                    .into(),
            ));
        }
        let element = header
            .element(name)
            .ok_or_else(|| layout(format!("no `{name}` element")))?;
        let mut start = header.len as u128;
        let mut end = header.len as u128;
        for (i, e) in header.elements.iter().enumerate() {
            let stride = e.fixed_stride().ok_or_else(|| {
                layout(format!(
                    "element `{}` has list properties, so its rows have no fixed size",
                    e.name
                ))
            })?;
            if i < element {
                start += e.count as u128 * stride as u128;
            }
            end += e.count as u128 * stride as u128;
        }
        if end != u128::from(file_len) {
            return Err(PlyError::Trailing {
                path: path.to_path_buf(),
                why: format!(
                    "more data than the header declares ({} bytes after the last element)",
                    u128::from(file_len) - end
                ),
            });
        }
        let e = &header.elements[element];
        let mut offsets = Vec::with_capacity(e.properties.len());
        let mut at = 0;
        for p in &e.properties {
            offsets.push(at);
            if let PropertyKind::Scalar(k) = p.kind {
                at += k.size();
            }
        }
        Ok(FixedRows {
            path: path.to_path_buf(),
            stride: at,
            start: start as u64,
            element,
            offsets,
            header,
        })
    }

    /// The streamed element's definition.
    pub fn def(&self) -> &ElementDef {
        &self.header.elements[self.element]
    }

    /// Rows of the streamed element.
    pub fn count(&self) -> usize {
        self.def().count
    }

    /// The value of property `p` in the raw bytes of one row.
    #[inline]
    pub fn value(&self, row: &[u8], p: usize) -> f64 {
        let PropertyKind::Scalar(k) = self.def().properties[p].kind else {
            unreachable!("FixedRows::open refuses list properties")
        };
        let o = self.offsets[p];
        k.decode(
            &row[o..o + k.size()],
            self.header.encoding == Encoding::BinaryBigEndian,
        )
    }

    /// Calls `f(first_row, bytes)` for consecutive chunks of at most `rows_per_chunk` rows, in
    /// file order; `bytes` holds whole rows of [`FixedRows::stride`] bytes.
    pub fn for_each_chunk<E: From<PlyError>>(
        &self,
        rows_per_chunk: usize,
        mut f: impl FnMut(usize, &[u8]) -> Result<(), E>,
    ) -> Result<(), E> {
        use std::io::{Read, Seek, SeekFrom};
        let io = |err| PlyError::Io {
            path: self.path.clone(),
            err,
        };
        let mut file = std::fs::File::open(&self.path).map_err(io)?;
        file.seek(SeekFrom::Start(self.start)).map_err(io)?;
        let per = rows_per_chunk.max(1);
        let mut buf = vec![0u8; per * self.stride];
        let mut row = 0;
        while row < self.count() {
            let n = per.min(self.count() - row);
            let chunk = &mut buf[..n * self.stride];
            file.read_exact(chunk).map_err(io)?;
            f(row, chunk)?;
            row += n;
        }
        Ok(())
    }
}

/// Reads a whole file for [`Reader::new`], naming it in the error.
pub fn read_file(path: &Path) -> Result<Vec<u8>, PlyError> {
    std::fs::read(path).map_err(|err| PlyError::Io {
        path: path.to_path_buf(),
        err,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("t.ply")
    }

    fn elements() -> Vec<ElementDef> {
        vec![
            ElementDef {
                name: "vertex".into(),
                count: 2,
                properties: vec![
                    PropertyDef::scalar("x", ScalarKind::F32),
                    PropertyDef::scalar("k", ScalarKind::U8),
                    PropertyDef::scalar("d", ScalarKind::F64),
                ],
            },
            ElementDef {
                name: "face".into(),
                count: 2,
                properties: vec![
                    PropertyDef::list("vertex_indices", ScalarKind::U8, ScalarKind::I32),
                    PropertyDef::scalar("id", ScalarKind::I16),
                ],
            },
        ]
    }

    fn encode(enc: Encoding) -> Vec<u8> {
        let mut w = RowWriter::new(enc, &["test"], &elements());
        for (x, k, d) in [(1.5, 7.0, -0.25), (-3.0, 255.0, 1e300)] {
            w.scalar(ScalarKind::F32, x);
            w.scalar(ScalarKind::U8, k);
            w.scalar(ScalarKind::F64, d);
            w.end_row();
        }
        w.list(ScalarKind::U8, ScalarKind::I32, &[0.0, 1.0, -5.0]);
        w.scalar(ScalarKind::I16, -300.0);
        w.end_row();
        w.list(ScalarKind::U8, ScalarKind::I32, &[]);
        w.scalar(ScalarKind::I16, 9.0);
        w.end_row();
        w.into_bytes()
    }

    /// Vertex rows, and per face its index list and id.
    type Decoded = (Vec<Vec<f64>>, Vec<(Vec<f64>, f64)>);

    fn decode(bytes: &[u8]) -> Result<Decoded, PlyError> {
        let mut r = Reader::new(p(), bytes)?;
        let mut v = Vec::new();
        r.read_element("vertex", |row| {
            v.push(row.values().to_vec());
            Ok::<(), PlyError>(())
        })?;
        let mut f = Vec::new();
        r.read_element("face", |row| {
            f.push((row.list(0).to_vec(), row.get(1)));
            Ok::<(), PlyError>(())
        })?;
        r.finish()?;
        Ok((v, f))
    }

    #[test]
    fn every_encoding_round_trips_scalars_and_lists() {
        for enc in [
            Encoding::Ascii,
            Encoding::BinaryLittleEndian,
            Encoding::BinaryBigEndian,
        ] {
            let bytes = encode(enc);
            let (v, f) = decode(&bytes).unwrap_or_else(|e| panic!("{enc:?}: {e}"));
            assert_eq!(v, vec![vec![1.5, 7.0, -0.25], vec![-3.0, 255.0, 1e300]]);
            assert_eq!(f, vec![(vec![0.0, 1.0, -5.0], -300.0), (vec![], 9.0)]);
        }
    }

    #[test]
    fn skipping_an_element_and_the_generic_path_agree() {
        let bytes = encode(Encoding::BinaryLittleEndian);
        let mut r = Reader::new(p(), &bytes).unwrap();
        let mut ids = Vec::new();
        r.read_element("face", |row| {
            ids.push(row.get(1));
            Ok::<(), PlyError>(())
        })
        .unwrap();
        assert_eq!(ids, vec![-300.0, 9.0]);
        assert!(matches!(
            r.read_element("vertex", |_| Ok::<(), PlyError>(())),
            Err(PlyError::Layout { .. })
        ));
    }

    #[test]
    fn header_errors_name_the_line() {
        let cases: [(&str, usize, &str); 9] = [
            ("plx\n", 1, "not a PLY"),
            ("ply\nformat ascii 2.0\nend_header\n", 2, "version"),
            ("ply\nformat text 1.0\nend_header\n", 2, "unknown format"),
            (
                "ply\nformat ascii 1.0\nproperty float x\nend_header\n",
                3,
                "before any element",
            ),
            (
                "ply\nformat ascii 1.0\nelement v -1\nend_header\n",
                3,
                "whole number",
            ),
            (
                "ply\nformat ascii 1.0\nelement v 0\nproperty floot x\nend_header\n",
                4,
                "floot",
            ),
            (
                "ply\nformat ascii 1.0\nelement v 0\nproperty list float int i\nend_header\n",
                4,
                "integer",
            ),
            (
                "ply\nformat ascii 1.0\nelement v 0\nproperty int a\nproperty int a\nend_header\n",
                5,
                "twice",
            ),
            (
                "ply\nformat ascii 1.0\nelement v 0\n",
                4,
                "ends before end_header",
            ),
        ];
        for (text, line, what) in cases {
            match Reader::new(p(), text.as_bytes()) {
                Err(e @ PlyError::Header { line: l, .. }) => {
                    assert_eq!(l, line, "{text:?}: {e}");
                    assert!(e.to_string().contains(what), "{text:?}: {e}");
                    assert!(e.to_string().starts_with("t.ply: "), "{e}");
                }
                other => panic!("{text:?}: {:?}", other.err()),
            }
        }
    }

    #[test]
    fn declared_sizes_beyond_the_file_fail_before_reading() {
        let text = "ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\nproperty double x\nproperty double y\nend_header\n";
        let e = Reader::new(p(), text.as_bytes()).err().unwrap();
        assert!(matches!(e, PlyError::Truncated { row: 0, .. }), "{e}");
        let text = "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nend_header\n1\n2\n";
        assert!(matches!(
            Reader::new(p(), text.as_bytes()),
            Err(PlyError::Size { .. })
        ));
        let text = "ply\nformat ascii 1.0\nelement vertex 5\nend_header\n";
        assert!(matches!(
            Reader::new(p(), text.as_bytes()),
            Err(PlyError::Size { .. })
        ));
    }

    #[test]
    fn payload_errors_name_element_row_and_line() {
        let good = String::from_utf8(encode(Encoding::Ascii)).unwrap();
        // The header has 11 lines, so vertex 0 is line 12 and face 0 line 14.
        let bad = good.replacen("255", "256", 1);
        let e = decode(bad.as_bytes()).unwrap_err();
        assert!(
            e.to_string()
                .contains("vertex 1 (line 13): `256` is not a uchar"),
            "{e}"
        );
        let extra = format!("{good}1 2 3\n");
        let e = decode(extra.as_bytes()).unwrap_err();
        assert!(matches!(e, PlyError::Trailing { .. }), "{e}");
        assert!(e.to_string().contains("line 16"), "{e}");
        let short = good.replacen("3 0 1 -5 -300", "3 0 1", 1);
        let e = decode(short.as_bytes()).unwrap_err();
        assert!(
            e.to_string()
                .contains("face 0 (line 14): no value for item 2"),
            "{e}"
        );

        let mut bin = encode(Encoding::BinaryLittleEndian);
        bin.push(0);
        assert!(matches!(decode(&bin), Err(PlyError::Trailing { .. })));
        bin.truncate(bin.len() - 4);
        let e = decode(&bin).unwrap_err();
        assert!(matches!(e, PlyError::Truncated { row: 1, .. }), "{e}");
        // A list count beyond the file.
        let mut big = encode(Encoding::BinaryLittleEndian);
        let at = big.len() - (1 + 2) - (1 + 12 + 2);
        big[at] = 200;
        let e = decode(&big).unwrap_err();
        assert!(matches!(e, PlyError::Truncated { row: 0, .. }), "{e}");
    }
}
