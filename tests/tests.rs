//! Every integration test, as modules of one test binary (one link of the crate instead of one
//! per file; ripgrep's layout). The shared fixtures are `common` (with `common::wall`), `boxes`
//! (the associate/fuse box scene) and `sim_labels` (simulated label features).
#[path = "common/boxes.rs"]
mod boxes;
mod common;
#[path = "common/sim_labels.rs"]
mod sim_labels;

mod architecture;
mod associate;
mod cache_lists;
mod cgal;
mod check;
mod cityjson;
mod citymodel;
mod cli;
mod cli_stages;
mod colmap;
mod eval;
mod export_3dtiles;
mod export_ply;
mod faults;
mod features;
mod fuse;
mod gt_reference;
mod hardening;
mod lift;
mod masks;
mod open3d_check;
mod openings;
mod progress;
mod query;
mod raycast;
mod raycast_packets;
mod readme;
mod real_inputs;
mod real_raycast;
mod refine;
mod render;
mod report;
mod run;
mod sam;
mod segment;
mod synth;
mod synth_masks;
mod textembed;
mod tile;
mod totals;
mod train;
mod view;
mod work;
