//! The run folder's files under `/files/…`: a request path is percent-decoded once, split at
//! `/`, and refused unless every segment is a plain name (no `..`, `.`, empty segment,
//! backslash, NUL or drive prefix); the joined path is then resolved with every symbolic link
//! (`canonicalize`) and must still lie inside the run folder, so neither an encoded `%2e%2e`
//! nor a link pointing out of the run reaches another file. Only regular files are served.
use std::path::{Path, PathBuf};

/// Why a path is refused (the server answers 403 with this text, or 404 for `Missing`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// Not a plain relative path inside the run folder.
    Outside(String),
    /// No such regular file.
    Missing(String),
}

/// Decodes `%XX` escapes; `None` for a bad escape or bytes that are not UTF-8.
pub fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = b.get(i + 1..i + 3)?;
            let hex = std::str::from_utf8(hex).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// The file of run folder `root` (canonical) that request path `rel` (the part after
/// `/files/`, percent-encoded) names.
pub fn resolve(root: &Path, rel: &str) -> Result<PathBuf, Refusal> {
    let outside = |why: &str| Refusal::Outside(format!("/files/{rel}: {why}"));
    let decoded = percent_decode(rel).ok_or_else(|| outside("bad percent-encoding"))?;
    if decoded.is_empty() {
        return Err(outside("no file named"));
    }
    let mut path = root.to_path_buf();
    for seg in decoded.split('/') {
        if seg.is_empty() || seg == "." || seg == ".." {
            return Err(outside("only plain names inside the run folder are served"));
        }
        if seg.contains(['\\', '\0', ':']) {
            return Err(outside("a path segment holds \\, NUL or :"));
        }
        path.push(seg);
    }
    let canon = path
        .canonicalize()
        .map_err(|_| Refusal::Missing(format!("/files/{rel}: no such file in the run folder")))?;
    if !canon.starts_with(root) {
        return Err(outside("it resolves outside the run folder"));
    }
    if !canon.is_file() {
        return Err(Refusal::Missing(format!(
            "/files/{rel}: not a regular file of the run folder"
        )));
    }
    Ok(canon)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%2Fb%2e%2E").as_deref(), Some("a/b.."));
        assert_eq!(percent_decode("%zz"), None);
        assert_eq!(percent_decode("%2"), None);
        assert_eq!(percent_decode("%ff"), None);
    }
}
