//! Decoding a CityGML file's bytes to UTF-8 text before it is parsed: byte-order marks
//! (UTF-8, UTF-16), the `encoding` of the XML declaration, ISO-8859-1 / windows-1252
//! transcoding that keeps the file's newlines, and errors that name the line of the first
//! bad byte.
use std::path::Path;

use super::CityGmlError;

/// The 1-based line of byte `offset` of `bytes`.
fn line_at(bytes: &[u8], offset: usize) -> u64 {
    1 + bytes[..offset.min(bytes.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count() as u64
}

/// The `encoding` of the XML declaration, if the text starts with one.
fn declared_encoding(bytes: &[u8]) -> Option<String> {
    let head = &bytes[..bytes.len().min(1024)];
    if !head.starts_with(b"<?xml") {
        return None;
    }
    let end = head.windows(2).position(|w| w == b"?>")?;
    let decl = std::str::from_utf8(&head[..end]).ok()?;
    let at = decl.find("encoding")?;
    let rest = decl[at + 8..].trim_start().strip_prefix('=')?.trim_start();
    let quote = rest.chars().next().filter(|c| *c == '"' || *c == '\'')?;
    let value = &rest[1..];
    Some(value[..value.find(quote)?].to_string())
}

/// windows-1252 code points of bytes 0x80..=0x9F (the WHATWG table; the five unassigned
/// bytes map to the C1 controls of the same value).
const CP1252_HIGH: [u16; 32] = [
    0x20AC, 0x81, 0x201A, 0x0192, 0x201E, 0x2026, 0x2020, 0x2021, 0x02C6, 0x2030, 0x0160, 0x2039,
    0x0152, 0x8D, 0x017D, 0x8F, 0x90, 0x2018, 0x2019, 0x201C, 0x201D, 0x2022, 0x2013, 0x2014,
    0x02DC, 0x2122, 0x0161, 0x203A, 0x0153, 0x9D, 0x017E, 0x0178,
];

/// The text of a CityGML file as UTF-8: UTF-8 (with or without BOM) as is, UTF-16 with a
/// BOM, and ISO-8859-1 / windows-1252 when the XML declaration names them, transcoded
/// (newlines are kept, so line numbers stay the file's own). Invalid UTF-8 is an error that
/// names the line of the first bad byte; an encoding the reader does not know is an error.
pub fn decode_text<'a>(
    path: &Path,
    bytes: &'a [u8],
) -> Result<std::borrow::Cow<'a, [u8]>, CityGmlError> {
    use std::borrow::Cow;
    let err = |line: u64, message: String| CityGmlError::Encoding {
        path: path.to_path_buf(),
        line,
        message,
    };
    let utf16 = |body: &[u8], big: bool| -> Result<Cow<'a, [u8]>, CityGmlError> {
        let units = body.chunks(2).map(|c| match (c, big) {
            ([a, b], true) => u16::from_be_bytes([*a, *b]),
            ([a, b], false) => u16::from_le_bytes([*a, *b]),
            _ => 0xDC00, // an odd trailing byte: a lone surrogate, reported below
        });
        let mut out = String::with_capacity(body.len() / 2);
        for c in char::decode_utf16(units) {
            match c {
                Ok(c) => out.push(c),
                Err(_) => {
                    let line = 1 + out.matches('\n').count() as u64;
                    return Err(err(line, "the file is not valid UTF-16".into()));
                }
            }
        }
        Ok(Cow::Owned(out.into_bytes()))
    };
    if let Some(body) = bytes.strip_prefix(b"\xFF\xFE") {
        return utf16(body, false);
    }
    if let Some(body) = bytes.strip_prefix(b"\xFE\xFF") {
        return utf16(body, true);
    }
    let bytes = crate::fsutil::strip_bom(bytes);
    let declared = declared_encoding(bytes);
    let norm = declared
        .as_deref()
        .map(|e| e.trim().to_ascii_lowercase().replace('_', "-"));
    match norm.as_deref() {
        None | Some("utf-8" | "utf8" | "us-ascii" | "ascii") => match std::str::from_utf8(bytes) {
            Ok(_) => Ok(Cow::Borrowed(bytes)),
            Err(e) => {
                let at = e.valid_up_to();
                Err(err(
                    line_at(bytes, at),
                    format!(
                        "the file is not valid UTF-8 (byte {:#04x}); if it is in another encoding, name it in the XML declaration, e.g. encoding=\"ISO-8859-1\"",
                        bytes[at]
                    ),
                ))
            }
        },
        Some("iso-8859-1" | "iso8859-1" | "latin1" | "latin-1" | "l1" | "iso-ir-100") => {
            Ok(Cow::Owned(
                bytes
                    .iter()
                    .map(|&b| char::from(b))
                    .collect::<String>()
                    .into_bytes(),
            ))
        }
        Some("windows-1252" | "cp1252" | "x-cp1252") => Ok(Cow::Owned(
            bytes
                .iter()
                .map(|&b| match b {
                    0x80..=0x9F => char::from_u32(u32::from(CP1252_HIGH[usize::from(b - 0x80)]))
                        .unwrap_or('\u{FFFD}'),
                    _ => char::from(b),
                })
                .collect::<String>()
                .into_bytes(),
        )),
        Some(_) => Err(err(
            1,
            format!(
                "the XML declaration names encoding \"{}\"; gs4city reads UTF-8, UTF-16 (with a byte-order mark), ISO-8859-1 and windows-1252",
                declared.unwrap_or_default()
            ),
        )),
    }
}
