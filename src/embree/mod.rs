//! The Embree FFI: the only module of gs4city allowed to use `unsafe`. It owns the RAII
//! wrappers of Embree's handles ([`Device`], [`Scene`] → [`CommittedScene`]) and the ray
//! queries (`intersect1`, `intersect16`). No Embree type leaves this module: callers see
//! [`Hit`], [`Packet16`] and [`EmbreeError`].
//!
//! Embree 3 (Debian 12) is what is built and tested here. `--features embree4` selects the
//! Embree 4 call signatures (`RTCIntersectArguments` instead of `RTCIntersectContext`) in
//! the two small `raw_intersect*` functions of `scene.rs`; that path cannot be compiled on
//! this machine (no Embree 4) and is untested.
#![allow(unsafe_code)]
mod device;
mod scene;
pub(crate) mod sys;

pub use device::{Device, EmbreeError};
pub use scene::{CommittedScene, Hit, Packet16, Scene};
