//! The Embree FFI: the only module of gs4city allowed to use `unsafe`. It owns the RAII
//! wrappers of Embree's handles ([`Device`], [`Scene`] → [`CommittedScene`]) and the ray
//! queries (`intersect1`, `intersect16`) and closest-point queries (`closest_point`,
//! `closest_point_filtered`, over `rtcPointQuery`). No Embree type leaves this module:
//! callers see [`Hit`], [`Packet16`], [`PointHit`] and [`EmbreeError`].
//!
//! Embree 3 (Debian 12) is what is built and tested here. `--features embree4` selects the
//! Embree 4 call signatures (`RTCIntersectArguments` instead of `RTCIntersectContext`) in
//! the two small `raw_intersect*` functions of `scene.rs`; that path cannot be compiled on
//! this machine (no Embree 4) and is untested. `rtcPointQuery` has the same signature in
//! Embree 3 and 4, so `query.rs` has a single path.
#![allow(unsafe_code)]
mod device;
mod query;
mod scene;
pub(crate) mod sys;

pub use device::{Device, EmbreeError};
pub use query::{PointHit, closest_point_on_triangle};
pub use scene::{CommittedScene, Hit, Packet16, Scene};
