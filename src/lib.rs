//! gs4city: hierarchical, queryable CityGML LoD3 semantics for 3D Gaussian Splatting
//! city scenes (the GS4City method), CPU-only.
//!
//! Readers and formats (depend on no stage): [`citygml`], [`mesh`], [`npy`], [`camera`],
//! [`splat`] (3DGS PLY). Stages: [`citymodel`], [`render`] (CPU rasterizer). See ARCHITECTURE.md for the data flow.
#![deny(unsafe_code)]

pub mod camera;
pub mod citygml;

pub mod cli;
pub(crate) mod embree;
pub mod fsutil;
pub mod imageio;
pub mod mesh;
pub mod npy;
pub mod render;
pub mod splat;
