//! The semantic table (`citymodel/semantics.json`): one [`Entity`] per CityGML object of the
//! hierarchy building → surface → opening, its typed [`Class`] and [`Level`], the reader that
//! checks the table, the writer, and the ancestor chains. A format: it imports no stage.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use crate::citygml::{Class, Level};
use crate::fsutil::{self, FsError};
use crate::mesh::{FaceLabel, TriMesh};

/// Errors of the semantic table.
#[derive(Debug, thiserror::Error)]
pub enum SemanticsError {
    #[error("{path}: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("{path}: {why}")]
    Labels { path: PathBuf, why: String },
    #[error(transparent)]
    Fs(#[from] FsError),
}

/// One row of the hierarchy table.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Entity {
    pub id: i32,
    pub object_id: String,
    pub class: Class,
    pub level: Level,
    pub parent: Option<i32>,
    pub building: i32,
    pub source: String,
    pub lod: Option<u8>,
    pub attributes: BTreeMap<String, serde_json::Value>,
}

/// Reads the `entities` of a `semantics.json` written by [`write()`] and checks the table:
/// ids equal row indices, every parent comes before its child (so the hierarchy has no
/// cycle and every ancestor walk ends), and `building` is the root of the parent chain.
pub fn read(path: &Path) -> Result<Vec<Entity>, SemanticsError> {
    let bad = |why: String| SemanticsError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read: {e}")))?;
    parse(path, &text)
}

/// [`read`] on text (`path` names the source in errors).
pub fn parse(path: &Path, text: &str) -> Result<Vec<Entity>, SemanticsError> {
    let bad = |why: String| SemanticsError::Invalid {
        path: path.to_path_buf(),
        why,
    };
    #[derive(serde::Deserialize)]
    struct File {
        entities: Vec<Entity>,
    }
    let f: File = serde_json::from_str(text)
        .map_err(|e| bad(format!("not a gs4city semantics.json: {e}")))?;
    for (i, e) in f.entities.iter().enumerate() {
        if e.id != i as i32 {
            return Err(bad(format!(
                "entity {} has id {}, expected {i}",
                e.object_id, e.id
            )));
        }
        if let Some(p) = e.parent
            && !(0..e.id).contains(&p)
        {
            return Err(bad(format!(
                "entity {} (id {}) names parent {p}, which is not an entity listed before it (a parent comes first; anything else could form a cycle)",
                e.object_id, e.id
            )));
        }
        let mut root = e.id;
        while let Some(p) = f.entities[root as usize].parent {
            root = p; // strictly decreasing ids: ends
        }
        if e.building != root {
            return Err(bad(format!(
                "entity {} (id {}) names building {}, but the root of its parent chain is {root}",
                e.object_id, e.id, e.building
            )));
        }
    }
    Ok(f.entities)
}

/// Checks a mesh's face labels against its hierarchy table: every id is −1 or a row of
/// `entities`, and the row's level matches (feature / surface / part). Call it before
/// raycasting; `path` names the mesh in the error.
pub fn check_mesh_labels(
    path: &Path,
    mesh: &TriMesh,
    entities: &[Entity],
) -> Result<(), SemanticsError> {
    let bad = |why: String| SemanticsError::Labels {
        path: path.to_path_buf(),
        why,
    };
    mesh.check_label_range(entities.len()).map_err(bad)?;
    let levels = [Level::Feature, Level::Surface, Level::Part];
    for (i, l) in mesh.labels.iter().enumerate() {
        for (&id, level) in l.ids().iter().zip(levels) {
            if id >= 0 && entities[id as usize].level != level {
                let e = &entities[id as usize];
                return Err(bad(format!(
                    "face {i}: its {} id {id} is entity {}, a {}",
                    level.name(),
                    e.object_id,
                    e.level.name()
                )));
            }
        }
    }
    Ok(())
}

/// Writes `semantics.json`: the entities, the sorted set of their class names and the levels.
pub fn write(path: &Path, entities: &[Entity]) -> Result<(), SemanticsError> {
    let class_names: Vec<&str> = entities
        .iter()
        .map(|e| e.class.name())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    fsutil::write_json(
        path,
        &serde_json::json!({ "entities": entities, "classes": class_names, "levels": ["feature", "surface", "part"] }),
    )?;
    Ok(())
}

/// CityGML attributes as `name=value unit` texts (the unit from `name.uom`, which is not listed
/// on its own), in name order.
pub fn attribute_texts(
    attrs: &std::collections::BTreeMap<String, serde_json::Value>,
) -> Vec<String> {
    attrs
        .iter()
        .filter(|(k, _)| !k.ends_with(".uom"))
        .map(|(k, v)| {
            let unit = attrs
                .get(&format!("{k}.uom"))
                .and_then(|u| u.as_str())
                .map(|u| format!(" {u}"))
                .unwrap_or_default();
            format!("{k}={v}{unit}")
        })
        .collect()
}

/// The ancestor chain of every entity of a semantic table: its `(feature, surface, part)` ids,
/// i.e. the nearest ancestor-or-self of each level (−1 where a level is missing). A surface
/// resets the part, a feature resets both. The table lists parents before children
/// ([`read`] checks this), so one forward pass suffices. This is the one
/// implementation of the hierarchy chain: face labels, the synthetic truth and the lifted
/// per-Gaussian hierarchy all use it.
pub fn chains(entities: &[Entity]) -> Vec<FaceLabel> {
    let mut out: Vec<FaceLabel> = Vec::with_capacity(entities.len());
    for (i, e) in entities.iter().enumerate() {
        let mut l = match e.parent {
            Some(p) if (p as usize) < i => out[p as usize],
            _ => FaceLabel::NONE,
        };
        let id = i as i32;
        match e.level {
            Level::Feature => {
                l = FaceLabel {
                    feature: id,
                    surface: -1,
                    part: -1,
                }
            }
            Level::Surface => {
                l.surface = id;
                l.part = -1;
            }
            Level::Part => l.part = id,
        }
        out.push(l);
    }
    out
}
