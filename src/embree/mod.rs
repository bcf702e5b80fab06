//! The Embree FFI: the only module of gs4city allowed to use `unsafe`. It owns the RAII
//! wrappers of Embree's handles ([`Device`], [`Scene`] → [`CommittedScene`]) and the ray
//! queries (`intersect1`; 8- and 16-wide packets, [`RayPacket`]) and closest-point queries (`closest_point`,
//! `closest_point_filtered`, over `rtcPointQuery`). No Embree type leaves this module:
//! callers see [`Hit`], [`Packet8`], [`Packet16`], [`PacketHit`], [`PacketWidth`], [`PointHit`] and [`EmbreeError`].
//!
//! Embree 3 (Debian 12) is what is built and tested here. `--features embree4` selects the
//! Embree 4 call signatures (`RTCIntersectArguments` instead of `RTCIntersectContext`) in
//! `raw_intersect1` of `scene.rs` and the packet queries of `packet.rs`; that path cannot be compiled on
//! this machine (no Embree 4) and is untested. `rtcPointQuery` has the same signature in
//! Embree 3 and 4, so `query.rs` has a single path.
#![allow(unsafe_code)]
mod device;
mod packet;
mod query;
mod scene;
pub(crate) mod sys;

pub use device::{Device, EmbreeError};
pub use packet::{Packet8, Packet16, PacketHit, PacketWidth, RayPacket};
pub use query::{PointHit, closest_point_on_triangle};
pub use scene::{CommittedScene, Hit, Scene};
