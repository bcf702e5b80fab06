//! NumPy `.npy` (format 1.0) reading and writing for the per-view maps (ID maps are
//! `int32`, depth `float32`), so Python users can `np.load` every output.
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::fsutil::{self, FsError};

/// Errors of `.npy` reading and writing.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error("cannot read {path}: {err}")]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{path}: not a usable .npy file: {why}")]
    Format { path: PathBuf, why: String },
    #[error("{path}: holds dtype {found}, expected {expected}")]
    Dtype {
        path: PathBuf,
        found: String,
        expected: &'static str,
    },
    #[error(
        "{path}: shape {} holds {expected} values but the payload has {found}",
        shape_text(shape)
    )]
    Size {
        path: PathBuf,
        shape: Vec<usize>,
        expected: usize,
        found: usize,
    },
    #[error(
        "{path}: shape {} holds more values than memory can address",
        shape_text(shape)
    )]
    Overflow { path: PathBuf, shape: Vec<usize> },
}

/// An element type that `.npy` can hold, stored little-endian.
pub trait NpyElement: Copy + Sized {
    /// The NumPy `descr` string, e.g. `<i4`.
    const DESCR: &'static str;
    /// Bytes per element.
    const SIZE: usize;
    /// Appends the little-endian bytes of `self`.
    fn put(self, out: &mut Vec<u8>);
    /// Reads one element from exactly `SIZE` bytes.
    fn get(bytes: &[u8]) -> Self;
}

macro_rules! npy_element {
    ($t:ty, $descr:expr) => {
        impl NpyElement for $t {
            const DESCR: &'static str = $descr;
            const SIZE: usize = std::mem::size_of::<$t>();
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn get(bytes: &[u8]) -> Self {
                <$t>::from_le_bytes(bytes.try_into().expect("caller passes SIZE bytes"))
            }
        }
    };
}
npy_element!(i32, "<i4");
npy_element!(u32, "<u4");
npy_element!(i64, "<i8");
npy_element!(f32, "<f4");
npy_element!(f64, "<f8");
npy_element!(u8, "|u1");
npy_element!(u16, "<u2");

/// A shape as NumPy prints it: `(3, 4)`, `(7,)`, `()`.
pub fn shape_text(shape: &[usize]) -> String {
    match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The `.npy` header (magic, version, length, dictionary) of an array of `T` with `shape`,
/// padded with spaces to at least `min_len` bytes (a multiple of 64 either way): a writer that
/// learns the shape only at the end reserves a header of fixed size and rewrites it in place.
pub fn header<T: NpyElement>(shape: &[usize], min_len: usize) -> Vec<u8> {
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}",
        T::DESCR,
        shape_text(shape)
    );
    // magic(6) + version(2) + len(2) + header + '\n' must be a multiple of 64.
    let mut total = 10 + header.len() + 1;
    if total < min_len {
        header.push_str(&" ".repeat(min_len - total));
        total = min_len;
    }
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out
}

/// Encodes `data` with `shape` (C order) as `.npy` bytes.
pub fn encode<T: NpyElement>(shape: &[usize], data: &[T]) -> Vec<u8> {
    assert_eq!(
        shape.iter().product::<usize>(),
        data.len(),
        "npy::encode: shape does not match data"
    );
    let mut out = header::<T>(shape, 0);
    out.reserve(data.len() * T::SIZE);
    for &v in data {
        v.put(&mut out);
    }
    out
}

/// Writes a `.npy` file atomically.
pub fn write<T: NpyElement>(path: &Path, shape: &[usize], data: &[T]) -> Result<(), NpyError> {
    let bytes = encode(shape, data);
    fsutil::atomic_write(path, |w| {
        w.write_all(&bytes).map_err(|err| {
            NpyError::Fs(FsError::Write {
                path: path.to_path_buf(),
                err,
            })
        })
    })
}

/// Reads a `.npy` file of element type `T`; returns `(shape, data)` in C order.
pub fn read<T: NpyElement>(path: &Path) -> Result<(Vec<usize>, Vec<T>), NpyError> {
    let bytes = std::fs::read(path).map_err(|err| NpyError::Read {
        path: path.to_path_buf(),
        err,
    })?;
    decode(path, &bytes)
}

/// Decodes `.npy` bytes (`path` only names the source in errors).
pub fn decode<T: NpyElement>(path: &Path, bytes: &[u8]) -> Result<(Vec<usize>, Vec<T>), NpyError> {
    let fmt = |why: &str| NpyError::Format {
        path: path.to_path_buf(),
        why: why.to_string(),
    };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(fmt("missing magic"));
    }
    let (hlen, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        _ => return Err(fmt("unsupported version")),
    };
    let header = start
        .checked_add(hlen)
        .and_then(|end| bytes.get(start..end))
        .ok_or_else(|| fmt("truncated header"))?;
    let header = std::str::from_utf8(header).map_err(|_| fmt("header is not text"))?;
    let descr = dict_value(header, "descr").ok_or_else(|| fmt("no descr"))?;
    let descr = descr
        .strip_prefix(['\'', '"'])
        .ok_or_else(|| fmt("descr is not a string"))?;
    let descr = &descr[..descr
        .find(['\'', '"'])
        .ok_or_else(|| fmt("descr is not a string"))?];
    let descr_norm = descr.replace('=', "<");
    if descr_norm != T::DESCR && !(T::SIZE == 1 && descr_norm.ends_with(&T::DESCR[1..])) {
        return Err(NpyError::Dtype {
            path: path.to_path_buf(),
            found: descr.to_string(),
            expected: T::DESCR,
        });
    }
    if dict_value(header, "fortran_order").is_some_and(|v| v.starts_with("True")) {
        return Err(fmt("Fortran order is not supported"));
    }
    let shape_txt = dict_value(header, "shape").ok_or_else(|| fmt("no shape"))?;
    let inner = shape_txt.trim().trim_start_matches('(');
    let bad_shape = || {
        let end = shape_txt.find(')').map_or(shape_txt.len(), |i| i + 1);
        let t: String = shape_txt[..end].chars().take(60).collect();
        fmt(&format!("its shape {t} is not a tuple of whole numbers"))
    };
    let inner = &inner[..inner.find(')').ok_or_else(bad_shape)?];
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| bad_shape()))
        .collect::<Result<Vec<_>, _>>()?;
    let n = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .filter(|n| n.checked_mul(T::SIZE).is_some())
        .ok_or_else(|| NpyError::Overflow {
            path: path.to_path_buf(),
            shape: shape.clone(),
        })?;
    let payload = &bytes[start + hlen..];
    if payload.len() != n * T::SIZE {
        return Err(NpyError::Size {
            path: path.to_path_buf(),
            shape,
            expected: n,
            found: payload.len() / T::SIZE,
        });
    }
    let data = payload.chunks_exact(T::SIZE).map(T::get).collect();
    Ok((shape, data))
}

fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header
        .find(&format!("'{key}'"))
        .or_else(|| header.find(&format!("\"{key}\"")))?;
    let rest = &header[at + key.len() + 2..];
    let colon = rest.find(':')?;
    Some(rest[colon + 1..].trim_start())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_alignment() {
        let data: Vec<i32> = (-6..6).collect();
        let bytes = encode(&[3, 4], &data);
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let (shape, back) = decode::<i32>(Path::new("mem"), &bytes).unwrap();
        assert_eq!(shape, vec![3, 4]);
        assert_eq!(back, data);
        let f = encode(&[2], &[1.5f32, f32::NAN]);
        let (_, g) = decode::<f32>(Path::new("mem"), &f).unwrap();
        assert_eq!(g[0], 1.5);
        assert!(g[1].is_nan());
        // The bytes NumPy writes for `np.save(f, np.array([7], dtype=np.uint8))` (NumPy 2.4):
        // a one-element shape is the tuple `(1,)`, the header padded to 128 bytes.
        let one = encode(&[1], &[7u8]);
        let mut numpy =
            b"\x93NUMPY\x01\x00v\x00{'descr': '|u1', 'fortran_order': False, 'shape': (1,), }"
                .to_vec();
        numpy.extend(std::iter::repeat_n(b' ', 60));
        numpy.extend(b"\n\x07");
        assert_eq!(one, numpy);
    }

    #[test]
    fn wrong_dtype_and_truncation_are_errors() {
        let bytes = encode(&[2, 2], &[1i32, 2, 3, 4]);
        assert!(matches!(
            decode::<f32>(Path::new("x.npy"), &bytes),
            Err(NpyError::Dtype { .. })
        ));
        assert!(matches!(
            decode::<i32>(Path::new("x.npy"), &bytes[..bytes.len() - 1]),
            Err(NpyError::Size { .. })
        ));
        assert!(matches!(
            decode::<i32>(Path::new("x.npy"), b"nope"),
            Err(NpyError::Format { .. })
        ));
    }
}
