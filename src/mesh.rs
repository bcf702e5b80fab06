//! The labelled triangle mesh handed from the `citymodel` stage to raycasting, and its
//! `mesh.ply` layout on the shared PLY layer [`crate::ply`] (`docs/design.md` fixes it; written
//! binary little-endian): `vertex {float x,y,z}`,
//! `face {list uchar int vertex_indices; int feature_id; int surface_id; int part_id}`.
//! Reading accepts any PLY encoding and scalar types that hold these values exactly, and
//! ignores extra properties and elements.
use std::path::{Path, PathBuf};

use crate::camera::SCENE_COORD_LIMIT;
use crate::fsutil::{self, FsError};
use crate::ply::{
    self, ElementDef, Encoding, PropertyDef, PropertyKind, Reader, RowWriter, ScalarKind,
};

/// The hierarchical ids of one face; −1 where a level is missing. Ids index `semantics.json`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct FaceLabel {
    pub feature: i32,
    pub surface: i32,
    pub part: i32,
}

impl FaceLabel {
    /// No entity at any level.
    pub const NONE: FaceLabel = FaceLabel {
        feature: -1,
        surface: -1,
        part: -1,
    };

    /// The ids in level order (feature, surface, part).
    pub fn ids(&self) -> [i32; 3] {
        [self.feature, self.surface, self.part]
    }
}

/// A triangle mesh in the scene frame (f32) with one [`FaceLabel`] per face.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<[f32; 3]>,
    pub faces: Vec<[u32; 3]>,
    pub labels: Vec<FaceLabel>,
}

/// Errors of `mesh.ply` reading and writing.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error(transparent)]
    Fs(#[from] FsError),
    #[error(transparent)]
    Ply(#[from] ply::PlyError),
    #[error("{path}: {why}")]
    Format { path: PathBuf, why: String },
}

/// The names of the label properties, in level order.
const LABEL_PROPS: [&str; 3] = ["feature_id", "surface_id", "part_id"];

impl TriMesh {
    /// Checks the invariants: one label per face, every index in range, label ids −1 or
    /// positive, vertices finite and within the scene frame's [`SCENE_COORD_LIMIT`].
    pub fn validate(&self) -> Result<(), String> {
        if self.labels.len() != self.faces.len() {
            return Err(format!(
                "{} faces but {} labels",
                self.faces.len(),
                self.labels.len()
            ));
        }
        let n = self.vertices.len();
        if let Some((i, f)) = self
            .faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&v| v as usize >= n))
        {
            return Err(format!(
                "face {i} uses vertices {}, {}, {} but there are {n} vertices",
                f[0], f[1], f[2]
            ));
        }
        if let Some((i, l)) = self
            .labels
            .iter()
            .enumerate()
            .find(|(_, l)| l.ids().iter().any(|&id| id < -1))
        {
            return Err(format!(
                "face {i} has label ids {}, {}, {}; an id is −1 (none) or an entity index ≥ 0",
                l.feature, l.surface, l.part
            ));
        }
        let lim = SCENE_COORD_LIMIT as f32;
        if let Some((i, v)) = self
            .vertices
            .iter()
            .enumerate()
            .find(|(_, v)| v.iter().any(|c| !c.is_finite() || c.abs() > lim))
        {
            return Err(format!(
                "vertex {i} at ({}, {}, {}) is not finite or lies beyond ±{SCENE_COORD_LIMIT:e}, the scene frame's limit",
                v[0], v[1], v[2]
            ));
        }
        Ok(())
    }

    /// Checks every label id against a semantic table of `entities` rows: each id is −1 or
    /// an index below `entities`. Call it before raycasting with the `semantics.json` the
    /// mesh came with (`semantics::check_mesh_labels` also checks the levels).
    pub fn check_label_range(&self, entities: usize) -> Result<(), String> {
        for (i, l) in self.labels.iter().enumerate() {
            for (level, &id) in ["feature", "surface", "part"].iter().zip(&l.ids()) {
                if id < -1 || (id >= 0 && id as usize >= entities) {
                    return Err(format!(
                        "face {i} has {level} id {id}, but the semantic table has {entities} entities (ids 0..{})",
                        entities.saturating_sub(1)
                    ));
                }
            }
        }
        Ok(())
    }

    fn elements(&self) -> [ElementDef; 2] {
        let int = |n: &str| PropertyDef::scalar(n, ScalarKind::I32);
        [
            ElementDef {
                name: "vertex".into(),
                count: self.vertices.len(),
                properties: ["x", "y", "z"]
                    .map(|n| PropertyDef::scalar(n, ScalarKind::F32))
                    .to_vec(),
            },
            ElementDef {
                name: "face".into(),
                count: self.faces.len(),
                properties: vec![
                    PropertyDef::list("vertex_indices", ScalarKind::U8, ScalarKind::I32),
                    int(LABEL_PROPS[0]),
                    int(LABEL_PROPS[1]),
                    int(LABEL_PROPS[2]),
                ],
            },
        ]
    }

    /// Encodes the mesh as `mesh.ply` bytes (binary little-endian).
    pub fn to_ply_bytes(&self) -> Vec<u8> {
        let mut w = RowWriter::new(
            Encoding::BinaryLittleEndian,
            &["gs4city citymodel mesh"],
            &self.elements(),
        );
        for v in &self.vertices {
            for &c in v {
                w.scalar(ScalarKind::F32, f64::from(c));
            }
        }
        for (f, l) in self.faces.iter().zip(&self.labels) {
            w.list(ScalarKind::U8, ScalarKind::I32, &f.map(f64::from));
            for id in l.ids() {
                w.scalar(ScalarKind::I32, f64::from(id));
            }
        }
        w.into_bytes()
    }

    /// Writes `mesh.ply` atomically.
    pub fn write_ply(&self, path: &Path) -> Result<(), MeshError> {
        fsutil::write_bytes(path, &self.to_ply_bytes())?;
        Ok(())
    }

    /// Reads a `mesh.ply` (the layout in the module docs) and validates it.
    pub fn read_ply(path: &Path) -> Result<TriMesh, MeshError> {
        let bytes = ply::read_file(path)?;
        Self::from_ply_bytes(path, &bytes)
    }

    /// Decodes `mesh.ply` bytes; `path` names the source in errors.
    pub fn from_ply_bytes(path: &Path, bytes: &[u8]) -> Result<TriMesh, MeshError> {
        let err = |why: String| MeshError::Format {
            path: path.to_path_buf(),
            why,
        };
        let mut reader = Reader::new(path, bytes)?;
        let header = reader.header().clone();
        let find = |elem: &str| {
            header
                .element(elem)
                .map(|e| &header.elements[e])
                .ok_or_else(|| err(format!("no `{elem}` element")))
        };
        let (vdef, fdef) = (find("vertex")?, find("face")?);
        let prop = |def: &ElementDef, names: &[&str]| {
            names.iter().find_map(|n| def.property(n)).ok_or_else(|| {
                err(format!(
                    "element `{}` has no property `{}`",
                    def.name, names[0]
                ))
            })
        };
        let xyz = [
            prop(vdef, &["x"])?,
            prop(vdef, &["y"])?,
            prop(vdef, &["z"])?,
        ];
        let idx = prop(fdef, &["vertex_indices", "vertex_index"])?;
        let ids = [
            prop(fdef, &[LABEL_PROPS[0]])?,
            prop(fdef, &[LABEL_PROPS[1]])?,
            prop(fdef, &[LABEL_PROPS[2]])?,
        ];
        if !matches!(fdef.properties[idx].kind, PropertyKind::List { item, .. } if !item.is_float())
        {
            return Err(err(format!(
                "face property `{}` must be a list of integers",
                fdef.properties[idx].name
            )));
        }
        for &p in &ids {
            if !matches!(fdef.properties[p].kind, PropertyKind::Scalar(k) if !k.is_float()) {
                return Err(err(format!(
                    "face property `{}` must be an integer scalar",
                    fdef.properties[p].name
                )));
            }
        }
        let (nv, nf) = (vdef.count, fdef.count);
        let mut mesh = TriMesh {
            vertices: Vec::with_capacity(nv),
            faces: Vec::with_capacity(nf),
            labels: Vec::with_capacity(nf),
        };
        reader.read_element("vertex", |row| {
            mesh.vertices.push(xyz.map(|p| row.get(p) as f32));
            Ok::<(), MeshError>(())
        })?;
        let row_err = |row: &ply::Row, why: String| {
            err(format!(
                "face {}{}: {why}",
                row.index,
                ply::at_line(row.line)
            ))
        };
        reader.read_element("face", |row| {
            let list = row.list(idx);
            let [a, b, c] = list else {
                return Err(row_err(
                    row,
                    format!("has {} vertices; a mesh.ply face is a triangle", list.len()),
                ));
            };
            let f = [*a, *b, *c];
            if f.iter().any(|&v| v < 0.0 || v >= nv as f64) {
                return Err(row_err(
                    row,
                    format!(
                        "vertex indices {}, {}, {} are outside 0..{nv}",
                        f[0], f[1], f[2]
                    ),
                ));
            }
            mesh.faces.push(f.map(|v| v as u32));
            let id = |p: usize| {
                let v = row.get(p);
                if (-1.0..=f64::from(i32::MAX)).contains(&v) {
                    Ok(v as i32)
                } else {
                    Err(row_err(
                        row,
                        format!(
                            "`{}` is {v}; an id is −1 (none) or an entity index ≥ 0",
                            fdef.properties[p].name
                        ),
                    ))
                }
            };
            mesh.labels.push(FaceLabel {
                feature: id(ids[0])?,
                surface: id(ids[1])?,
                part: id(ids[2])?,
            });
            Ok(())
        })?;
        reader.finish()?;
        mesh.validate().map_err(err)?;
        Ok(mesh)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad() -> TriMesh {
        TriMesh {
            vertices: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.5],
            ],
            faces: vec![[0, 1, 2], [0, 2, 3]],
            labels: vec![
                FaceLabel {
                    feature: 0,
                    surface: 1,
                    part: -1,
                },
                FaceLabel {
                    feature: 0,
                    surface: 1,
                    part: 2,
                },
            ],
        }
    }

    #[test]
    fn ply_round_trip_is_exact() {
        let m = quad();
        let bytes = m.to_ply_bytes();
        let back = TriMesh::from_ply_bytes(Path::new("m.ply"), &bytes).unwrap();
        assert_eq!(back, m);
    }

    #[test]
    fn truncated_and_out_of_range_are_errors() {
        let bytes = quad().to_ply_bytes();
        let e = TriMesh::from_ply_bytes(Path::new("m.ply"), &bytes[..bytes.len() - 3]).unwrap_err();
        assert!(e.to_string().contains("m.ply"), "{e}");
        let mut bad = quad();
        bad.faces[1][2] = 9;
        let e = TriMesh::from_ply_bytes(Path::new("m.ply"), &bad.to_ply_bytes()).unwrap_err();
        assert!(e.to_string().contains("face 1"), "{e}");
    }
}
