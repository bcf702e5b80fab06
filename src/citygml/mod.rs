//! CityGML 1.0 / 2.0 / 3.0 reader (a reader: depends on no pipeline stage).
//!
//! Streams the XML with quick-xml, keeps Buildings, BuildingParts, installations, thematic
//! surfaces and openings with their attributes and LoD geometry (f64, file CRS), resolves
//! `xlink:href` so shared polygons are counted once, and chooses LoD3 per building with a
//! named fallback to LoD2/LoD1. Unknown elements are skipped and counted.
mod appearance;
mod encoding;
mod geometry;
mod hierarchy;
mod ids;
mod model;
mod reader;

use std::path::PathBuf;

pub use ids::{disambiguate, unique_id};
pub use model::*;
pub use reader::{read, read_bytes};

/// Errors of CityGML reading; each names the file and the line (and gml:id where there is one).
#[derive(Debug, thiserror::Error)]
pub enum CityGmlError {
    #[error("cannot read {path}: {err}")]
    Open { path: PathBuf, err: std::io::Error },
    #[error("{path}:{line}: {message}")]
    Encoding {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{path}:{line}: {message}")]
    Content {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{path}:{line}: malformed XML: {message}")]
    Xml {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{path}:{line}: file ends inside {open} open element(s): truncated?")]
    Truncated {
        path: PathBuf,
        line: u64,
        open: usize,
    },
    #[error(
        "{path}:{line}: not a CityGML file (root element {root}, expected a CityGML 1.0/2.0/3.0 core:CityModel)"
    )]
    NotCityGml {
        path: PathBuf,
        line: u64,
        root: String,
    },
    #[error("{path}:{line}: {}{message}", id.as_ref().map(|i| format!("polygon {i}: ")).unwrap_or_default())]
    Geometry {
        path: PathBuf,
        line: u64,
        id: Option<String>,
        message: String,
    },
}
