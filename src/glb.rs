//! glTF 2.0 binary files (`.glb`): a writer of one-buffer assets — typed accessors over buffer
//! views in one binary chunk, the JSON written by the caller — and the reader of the same
//! layout (header, JSON chunk, BIN chunk; sizes checked before use).
//!
//! Layout rules the writer keeps (glTF 2.0 §3.6, §4.4; `EXT_structural_metadata`): every buffer
//! view starts on an 8-byte boundary, vertex attributes are 4-byte `float` elements, the JSON
//! chunk is padded with spaces and the BIN chunk with zeros to a multiple of 4, and `POSITION`
//! accessors carry `min`/`max`.
use serde_json::{Value, json};

/// `componentType` of 32-bit floats.
pub const FLOAT: u32 = 5126;
/// `componentType` of unsigned 32-bit integers.
pub const UNSIGNED_INT: u32 = 5125;
/// `componentType` of unsigned bytes.
pub const UNSIGNED_BYTE: u32 = 5121;
/// `bufferView.target` of vertex attributes.
pub const ARRAY_BUFFER: u32 = 34962;

const MAGIC: u32 = 0x4654_6C67; // "glTF"
const JSON_CHUNK: u32 = 0x4E4F_534A; // "JSON"
const BIN_CHUNK: u32 = 0x004E_4942; // "BIN\0"

/// Errors of the glb reader and writer.
#[derive(Debug, thiserror::Error)]
pub enum GlbError {
    #[error("{what}: not a glTF binary: {why}")]
    Format { what: String, why: String },
    #[error("the binary chunk would exceed 4 GiB ({0} bytes): split the content")]
    TooLarge(usize),
}

/// Builds the binary chunk and the `bufferViews` / `accessors` arrays of one asset.
#[derive(Debug, Default)]
pub struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

/// The glTF `type` of an accessor with `n` components.
fn type_name(n: usize) -> &'static str {
    match n {
        1 => "SCALAR",
        2 => "VEC2",
        3 => "VEC3",
        4 => "VEC4",
        _ => "MAT4",
    }
}

impl Builder {
    /// An empty asset.
    pub fn new() -> Builder {
        Builder::default()
    }

    /// Appends `bytes` as a buffer view (8-byte aligned) and returns its index. Empty `bytes`
    /// (a string column of empty strings) become one zero byte: glTF forbids empty views.
    pub fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        while self.bin.len() % 8 != 0 {
            self.bin.push(0);
        }
        let bytes = if bytes.is_empty() { &[0u8][..] } else { bytes };
        let mut v = json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()});
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        self.bin.extend_from_slice(bytes);
        self.views.push(v);
        self.views.len() - 1
    }

    /// A vertex attribute accessor of `n`-component float elements (`data.len()` a multiple of
    /// `n`); with `bounds`, its per-component `min` and `max`. Returns the accessor index.
    pub fn floats(&mut self, data: &[f32], n: usize, bounds: bool) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|x| x.to_le_bytes()).collect();
        let view = self.view(&bytes, Some(ARRAY_BUFFER));
        let mut a = json!({
            "bufferView": view,
            "componentType": FLOAT,
            "count": data.len() / n,
            "type": type_name(n),
        });
        if bounds && !data.is_empty() {
            let mut lo = vec![f32::INFINITY; n];
            let mut hi = vec![f32::NEG_INFINITY; n];
            for e in data.chunks_exact(n) {
                for k in 0..n {
                    lo[k] = lo[k].min(e[k]);
                    hi[k] = hi[k].max(e[k]);
                }
            }
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    /// An accessor with no buffer view (its data comes from an extension, e.g. SPZ): `count`
    /// elements of `n` components of `component_type`, `normalized`, with `min`/`max` when
    /// given. Returns the accessor index.
    pub fn declared(
        &mut self,
        component_type: u32,
        n: usize,
        count: usize,
        normalized: bool,
        bounds: Option<(Vec<f32>, Vec<f32>)>,
    ) -> usize {
        let mut a = json!({"componentType": component_type, "count": count, "type": type_name(n)});
        if normalized {
            a["normalized"] = json!(true);
        }
        if let Some((lo, hi)) = bounds {
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    /// The asset: `json` (everything but `buffers`, `bufferViews` and `accessors`, which are
    /// set here) and the binary chunk, as the bytes of a `.glb` file.
    pub fn finish(self, mut json: Value) -> Result<Vec<u8>, GlbError> {
        json["buffers"] = json!([{"byteLength": self.bin.len()}]);
        json["bufferViews"] = Value::Array(self.views);
        json["accessors"] = Value::Array(self.accessors);
        let mut text = serde_json::to_vec(&json).expect("a JSON value serialises");
        while text.len() % 4 != 0 {
            text.push(b' ');
        }
        let mut bin = self.bin;
        while bin.len() % 4 != 0 {
            bin.push(0);
        }
        let total = 12 + 8 + text.len() + 8 + bin.len();
        let total32 = u32::try_from(total).map_err(|_| GlbError::TooLarge(total))?;
        let mut out = Vec::with_capacity(total);
        for w in [MAGIC, 2, total32, text.len() as u32, JSON_CHUNK] {
            out.extend_from_slice(&w.to_le_bytes());
        }
        out.extend_from_slice(&text);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(&BIN_CHUNK.to_le_bytes());
        out.extend_from_slice(&bin);
        Ok(out)
    }
}

/// The JSON and the binary chunk of a `.glb` (`what` names it in errors).
pub fn read(what: &str, bytes: &[u8]) -> Result<(Value, Vec<u8>), GlbError> {
    let fail = |why: String| GlbError::Format {
        what: what.to_string(),
        why,
    };
    let word = |at: usize| -> Result<u32, GlbError> {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .ok_or_else(|| fail(format!("truncated at byte {at} of {}", bytes.len())))
    };
    if word(0)? != MAGIC || word(4)? != 2 {
        return Err(fail("no `glTF` version 2 header".into()));
    }
    if word(8)? as usize != bytes.len() {
        return Err(fail(format!(
            "the header says {} bytes, the file has {}",
            word(8)?,
            bytes.len()
        )));
    }
    let (jlen, jtype) = (word(12)? as usize, word(16)?);
    if jtype != JSON_CHUNK || 20 + jlen > bytes.len() {
        return Err(fail(
            "the first chunk is not a JSON chunk inside the file".into(),
        ));
    }
    let json: Value = serde_json::from_slice(&bytes[20..20 + jlen])
        .map_err(|e| fail(format!("JSON chunk: {e}")))?;
    let at = 20 + jlen;
    let bin = if at < bytes.len() {
        let (blen, btype) = (word(at)? as usize, word(at + 4)?);
        if btype != BIN_CHUNK || at + 8 + blen > bytes.len() {
            return Err(fail(
                "the second chunk is not a BIN chunk inside the file".into(),
            ));
        }
        bytes[at + 8..at + 8 + blen].to_vec()
    } else {
        Vec::new()
    };
    Ok((json, bin))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn written_assets_read_back_with_aligned_chunks() {
        let mut b = Builder::new();
        let a = b.floats(&[1.0, 2.0, 3.0, -1.0, 5.0, 0.5], 3, true);
        let v = b.view(&[1, 2, 3], None);
        let bytes = b.finish(json!({"asset": {"version": "2.0"}})).unwrap();
        assert_eq!(bytes.len() % 4, 0);
        let (j, bin) = read("t.glb", &bytes).unwrap();
        assert_eq!(j["accessors"][a]["min"], json!([-1.0, 2.0, 0.5]));
        assert_eq!(j["accessors"][a]["max"], json!([1.0, 5.0, 3.0]));
        assert_eq!(j["bufferViews"][v]["byteOffset"], json!(24));
        assert_eq!(&bin[24..27], &[1, 2, 3]);
        assert_eq!(f32::from_le_bytes(bin[12..16].try_into().unwrap()), -1.0);
        assert!(read("t.glb", &bytes[..bytes.len() - 4]).is_err());
    }
}
