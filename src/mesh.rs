//! The labelled triangle mesh handed from the `citymodel` stage to raycasting, and its
//! `mesh.ply` file (binary little-endian; DESIGN.md fixes the layout):
//! `vertex {float x,y,z}`, `face {list uchar int vertex_indices; int feature_id; int surface_id; int part_id}`.
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::fsutil::{self, FsError};

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
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {why}")]
    Format { path: PathBuf, why: String },
}

const HEADER_TAIL: &str = "property float x\nproperty float y\nproperty float z\n";
const FACE_PROPS: &str = "property list uchar int vertex_indices\nproperty int feature_id\nproperty int surface_id\nproperty int part_id\nend_header\n";

impl TriMesh {
    /// Checks the invariants: one label per face, every index in range, finite vertices.
    pub fn validate(&self) -> Result<(), String> {
        if self.labels.len() != self.faces.len() {
            return Err(format!(
                "{} faces but {} labels",
                self.faces.len(),
                self.labels.len()
            ));
        }
        let n = self.vertices.len() as u32;
        if let Some((i, f)) = self
            .faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&v| v >= n))
        {
            return Err(format!(
                "face {i} references vertex {:?} but there are {n} vertices",
                f
            ));
        }
        if let Some(i) = self
            .vertices
            .iter()
            .position(|v| v.iter().any(|c| !c.is_finite()))
        {
            return Err(format!("vertex {i} is not finite"));
        }
        Ok(())
    }

    /// Encodes the mesh as `mesh.ply` bytes.
    pub fn to_ply_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(64 + self.vertices.len() * 12 + self.faces.len() * 25);
        out.extend_from_slice(
            format!(
                "ply\nformat binary_little_endian 1.0\ncomment gs4city citymodel mesh\nelement vertex {}\n{HEADER_TAIL}element face {}\n{FACE_PROPS}",
                self.vertices.len(),
                self.faces.len()
            )
            .as_bytes(),
        );
        for v in &self.vertices {
            for c in v {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for (f, l) in self.faces.iter().zip(&self.labels) {
            out.push(3);
            for &i in f {
                out.extend_from_slice(&(i as i32).to_le_bytes());
            }
            for id in [l.feature, l.surface, l.part] {
                out.extend_from_slice(&id.to_le_bytes());
            }
        }
        out
    }

    /// Writes `mesh.ply` atomically.
    pub fn write_ply(&self, path: &Path) -> Result<(), MeshError> {
        let bytes = self.to_ply_bytes();
        fsutil::atomic_write(path, |w| {
            w.write_all(&bytes).map_err(|source| {
                MeshError::Fs(FsError::Write {
                    path: path.to_path_buf(),
                    source,
                })
            })
        })
    }

    /// Reads a `mesh.ply` written by [`TriMesh::write_ply`] (the layout DESIGN.md fixes).
    pub fn read_ply(path: &Path) -> Result<TriMesh, MeshError> {
        let bytes = std::fs::read(path).map_err(|source| MeshError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_ply_bytes(path, &bytes)
    }

    /// Decodes `mesh.ply` bytes; `path` names the source in errors.
    pub fn from_ply_bytes(path: &Path, bytes: &[u8]) -> Result<TriMesh, MeshError> {
        let err = |why: String| MeshError::Format {
            path: path.to_path_buf(),
            why,
        };
        let end = find(bytes, b"end_header\n").ok_or_else(|| err("no PLY end_header".into()))? + 11;
        let header =
            std::str::from_utf8(&bytes[..end]).map_err(|_| err("header is not text".into()))?;
        if !header.starts_with("ply\n") || !header.contains("format binary_little_endian 1.0\n") {
            return Err(err("not a binary little-endian PLY".into()));
        }
        let count = |elem: &str| -> Result<usize, MeshError> {
            header
                .lines()
                .find_map(|l| l.strip_prefix(&format!("element {elem} ")))
                .and_then(|n| n.trim().parse().ok())
                .ok_or_else(|| err(format!("no 'element {elem}' count")))
        };
        let (nv, nf) = (count("vertex")?, count("face")?);
        if !header.contains(HEADER_TAIL) || !header.ends_with(FACE_PROPS) {
            return Err(err("properties differ from the gs4city mesh layout (x y z; vertex_indices feature_id surface_id part_id)".into()));
        }
        let body = &bytes[end..];
        let need = nv * 12 + nf * 25;
        if body.len() != need {
            return Err(err(format!(
                "payload has {} bytes, header announces {need}",
                body.len()
            )));
        }
        let f32_at = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().expect("4 bytes"));
        let i32_at = |o: usize| i32::from_le_bytes(body[o..o + 4].try_into().expect("4 bytes"));
        let vertices = (0..nv)
            .map(|i| [f32_at(i * 12), f32_at(i * 12 + 4), f32_at(i * 12 + 8)])
            .collect();
        let mut faces = Vec::with_capacity(nf);
        let mut labels = Vec::with_capacity(nf);
        for i in 0..nf {
            let o = nv * 12 + i * 25;
            if body[o] != 3 {
                return Err(err(format!(
                    "face {i} has {} vertices, expected 3",
                    body[o]
                )));
            }
            let idx = [i32_at(o + 1), i32_at(o + 5), i32_at(o + 9)];
            if idx.iter().any(|&v| v < 0 || v as usize >= nv) {
                return Err(err(format!(
                    "face {i} has vertex indices {idx:?} outside 0..{nv}"
                )));
            }
            faces.push(idx.map(|v| v as u32));
            labels.push(FaceLabel {
                feature: i32_at(o + 13),
                surface: i32_at(o + 17),
                part: i32_at(o + 21),
            });
        }
        let mesh = TriMesh {
            vertices,
            faces,
            labels,
        };
        mesh.validate().map_err(err)?;
        Ok(mesh)
    }
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len())
        .take(1 << 16)
        .position(|w| w == needle)
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
