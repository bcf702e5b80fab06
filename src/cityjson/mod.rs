//! CityJSON 1.0 / 1.1 / 2.0 and CityJSONSeq reader (a format: depends on no pipeline stage).
//!
//! Produces the same typed [`CityModel`] as the CityGML reader, so every stage works
//! unchanged: Buildings, BuildingParts, BuildingInstallations and BuildingConstructiveElements
//! are city objects (hierarchy from `parents`/`children`); the semantic surfaces of their
//! geometry (`semantics.surfaces`) become the surface and part objects (a Window's `parent`
//! is its wall); `attributes` are kept (`{"value": v, "uom": u}` becomes `name` and
//! `name.uom`, as the CityGML reader writes units). Quantised vertices are decoded with the
//! `transform` in f64; the CRS is `metadata.referenceSystem`. A CityJSONSeq file
//! (`.city.jsonl`) is read line by line: its first line is the header (version, transform,
//! CRS), every further line a `CityJSONFeature` with its own vertex list.
//!
//! Order: city objects are visited from the roots (objects without `parents`, sorted by id;
//! in a CityJSONSeq feature by feature) down their `children`, each followed by its semantic
//! surfaces (parents first), so a parent always precedes its children. A semantic surface
//! is named by its `id` member when it has one (converters keep the CityGML gml:id there),
//! otherwise `<parent id>/<Class>[k]` as the CityGML reader derives ids.
//!
//! LoD: per building, the geometries of LoD 3 are used, else LoD 2, else LoD 1 (as for
//! CityGML), and among several of one level (`2.0`, `2.2`) the highest. Other geometries are
//! read and checked but left unused. Errors name the file (and the line in a CityJSONSeq),
//! the CityObject and what is wrong: a missing or malformed `transform`, a vertex index that
//! does not exist, an empty surface or ring, a grossly non-planar surface, wrong JSON types.
//!
//! [`write()`] is the inverse: a model of either encoding → one CityJSON 2.0 document (used by
//! `synth` to hand the pipeline a model without some of its openings).
mod build;
mod write;

use std::path::{Path, PathBuf};

use crate::citygml::{self, CityGmlError, CityModel};

pub use build::{PLANARITY_MIN, PLANARITY_TOLERANCE};
pub use write::{WRITE_SCALE, to_json, write};

/// Errors of CityJSON reading; each names the file (and the line of a CityJSONSeq feature)
/// and the CityObject concerned.
#[derive(Debug, thiserror::Error)]
pub enum CityJsonError {
    #[error("cannot read {path}: {err}")]
    Open { path: PathBuf, err: std::io::Error },
    #[error("{path}:{line}: malformed JSON: {message}")]
    Json {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{}", located(path, *line, object.as_deref(), message))]
    Content {
        path: PathBuf,
        /// Line of the CityJSONSeq feature; `None` in a CityJSON document.
        line: Option<u64>,
        /// The CityObject's id, where the problem lies inside one.
        object: Option<String>,
        message: String,
    },
    #[error(transparent)]
    CityGml(#[from] CityGmlError),
}

fn located(path: &Path, line: Option<u64>, object: Option<&str>, message: &str) -> String {
    let mut s = path.display().to_string();
    if let Some(l) = line {
        s.push_str(&format!(":{l}"));
    }
    s.push_str(": ");
    if let Some(o) = object {
        s.push_str(&format!("CityObject \"{o}\": "));
    }
    s.push_str(message);
    s
}

/// Whether `path` names a CityJSON file by its name: `*.json`, `*.city.json`, `*.jsonl`,
/// `*.city.jsonl` (case-insensitive).
pub fn is_cityjson_name(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json") || e.eq_ignore_ascii_case("jsonl"))
}

/// Whether `path` is a CityJSONSeq file (`*.jsonl`).
fn is_seq_name(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("jsonl"))
}

/// Whether a file found in a city-model folder is a city model: CityGML (`*.gml`, `*.xml`),
/// CityJSONSeq (`*.jsonl`), `*.city.json`, or another `*.json` whose first 4 KiB declare
/// `"type": "CityJSON"` (so `alignment.json` beside the model is not taken for one). The one
/// test every folder search of the project uses.
pub fn is_model_file(path: &Path) -> bool {
    let Some(ext) = path.extension() else {
        return false;
    };
    if ext.eq_ignore_ascii_case("gml")
        || ext.eq_ignore_ascii_case("xml")
        || ext.eq_ignore_ascii_case("jsonl")
    {
        return true;
    }
    if !ext.eq_ignore_ascii_case("json") {
        return false;
    }
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if name.ends_with(".city.json") {
        return true;
    }
    use std::io::Read;
    let mut head = Vec::with_capacity(4096);
    let Ok(f) = std::fs::File::open(path) else {
        return false;
    };
    if f.take(4096).read_to_end(&mut head).is_err() {
        return false;
    }
    let text = String::from_utf8_lossy(&head);
    let compact: String = text.chars().filter(|c| !c.is_whitespace()).collect();
    compact.contains("\"type\":\"CityJSON\"")
}

/// Reads a city model of either encoding: CityJSON / CityJSONSeq by the file name
/// ([`is_cityjson_name`]), CityGML otherwise.
pub fn read_any(path: &Path) -> Result<CityModel, CityJsonError> {
    if is_cityjson_name(path) {
        read(path)
    } else {
        Ok(citygml::read(path)?)
    }
}

/// Reads a CityJSON document, or a CityJSONSeq stream when the name ends in `.jsonl`.
pub fn read(path: &Path) -> Result<CityModel, CityJsonError> {
    if is_seq_name(path) {
        build::read_seq(path)
    } else {
        let bytes = std::fs::read(path).map_err(|err| CityJsonError::Open {
            path: path.to_path_buf(),
            err,
        })?;
        read_bytes(path, &bytes)
    }
}

/// Reads a CityJSON document from bytes (`path` names the source in messages).
pub fn read_bytes(path: &Path, bytes: &[u8]) -> Result<CityModel, CityJsonError> {
    build::read_document(path, bytes)
}
