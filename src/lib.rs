//! gs4city: hierarchical, queryable CityGML LoD3 semantics for 3D Gaussian Splatting
//! city scenes (the GS4City method), CPU-only.
//!
//! Readers and formats (depend on no stage): [`citygml`], [`colmap`], [`splat`] (3DGS PLY),
//! [`mesh`], [`ply`] (the PLY format under `splat` and `mesh`), [`npy`], [`onnxproto`] (keeping a subset of an ONNX graph's outputs), [`camera`], [`imageio`], [`sam`] (SAM JSON / COCO RLE, mask and prompt features; `synth::masks` simulates them for the synthetic benchmark).
//! Stages: [`citymodel`], [`refine`], [`raycast`], [`render`], [`masks`], [`associate`], [`fuse`], [`lift`], [`train`], [`eval`], [`query`]. See ARCHITECTURE.md for the data flow.
#![deny(unsafe_code)]

pub mod alignment;
pub mod associate;
pub mod bundled;
pub mod cache;
pub mod camera;
pub mod check;
pub mod citygml;
pub mod cityjson;
pub mod citymodel;
pub mod classes;
pub mod cli;
pub mod colmap;
pub mod crs;
pub mod embree;
pub mod eval;
pub mod fastmath;
pub mod fsutil;
pub mod fuse;
pub mod geotag;
pub mod glb;
pub mod groups;
pub mod hash;
pub mod idmap;
pub mod imageio;
pub mod inspect;
pub mod labels;
pub mod layout;
pub mod lift;

pub mod maskfile;
pub mod masks;
pub mod mesh;
pub mod npy;
pub mod numfmt;
pub mod onnxproto;
pub mod openings;
pub mod ply;
pub mod prediction;
pub mod progress;
pub mod query;
pub mod raycast;
pub mod refine;
pub mod render;
pub mod run;
pub mod sam;
pub mod scene;
pub mod segment;
pub mod selection;
pub mod semantics;
pub mod splat;
pub mod spz;
pub mod synth;
pub mod textembed;
pub mod tile;
pub mod train;
pub mod view;
pub mod vote;
