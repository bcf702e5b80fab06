//! Ray packets of 8 and 16 lanes (`rtcIntersect8` / `rtcIntersect16`), filled and read in
//! place in Embree's own structure-of-arrays layout, so that no per-lane copy or
//! `Option<Hit>` array stands between the caller's ray generation and the traversal.
//!
//! Which width to use is [`PacketWidth::native`]'s answer: 16 lanes where the CPU reports
//! AVX-512 and the Embree build traces 16-wide packets natively, 8 where it reports AVX2
//! and Embree has native 8-wide packets, else 8 (Embree emulates the width it lacks).
use super::device::Device;
use super::scene::CommittedScene;
use super::sys;

/// `RTC_INVALID_GEOMETRY_ID`.
const INVALID_GEOMETRY_ID: u32 = u32::MAX;

/// The number of lanes of a ray packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum PacketWidth {
    /// `rtcIntersect8`: 8 rays (tiles of 4×2 pixels).
    W8,
    /// `rtcIntersect16`: 16 rays (tiles of 4×4 pixels).
    W16,
}

impl PacketWidth {
    /// Lanes per packet.
    pub fn lanes(self) -> usize {
        match self {
            PacketWidth::W8 => 8,
            PacketWidth::W16 => 16,
        }
    }

    /// The widest packet this CPU and this Embree build trace natively: 16 when the CPU
    /// reports AVX-512F (`is_x86_feature_detected!`) and the device reports
    /// `RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED`; otherwise 8.
    pub fn native(device: &Device) -> PacketWidth {
        // SAFETY: the device handle is live (held by `device`); the property ids are
        // Embree's own constants.
        let ray16 = unsafe {
            sys::rtcGetDeviceProperty(
                device.inner.raw(),
                sys::RTCDeviceProperty::RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED,
            )
        } == 1;
        if ray16 && cpu_has_avx512() {
            PacketWidth::W16
        } else {
            PacketWidth::W8
        }
    }
}

#[cfg(target_arch = "x86_64")]
fn cpu_has_avx512() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
}

#[cfg(not(target_arch = "x86_64"))]
fn cpu_has_avx512() -> bool {
    false
}

/// One lane's hit (as [`super::Hit`], without barycentrics and normal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PacketHit {
    /// Distance along the ray direction (in units of the direction's length).
    pub t: f32,
    /// Triangle index within its geometry.
    pub prim_id: u32,
    /// Geometry id.
    pub geom_id: u32,
}

/// A packet of rays traced together. Implemented only here, for [`Packet8`] and
/// [`Packet16`]; every lane starts inactive.
pub trait RayPacket: private::Sealed + Sized {
    /// Lanes of the packet.
    const LANES: usize;
    /// An empty packet (every lane inactive).
    fn empty() -> Self;
    /// Makes lane `k` active with the ray `org + t·dir`, `t ∈ [0, tfar]`, not yet hit.
    fn set(&mut self, k: usize, org: [f32; 3], dir: [f32; 3], tfar: f32) {
        self.set_segment(k, org, dir, 0.0, tfar);
    }
    /// Makes lane `k` active with the segment `org + t·dir`, `t ∈ [tnear, tfar]`.
    fn set_segment(&mut self, k: usize, org: [f32; 3], dir: [f32; 3], tnear: f32, tfar: f32);
    /// Whether lane `k` is active.
    fn is_active(&self, k: usize) -> bool;
    /// Whether any lane is active.
    fn any_active(&self) -> bool;
    /// Traces the active lanes (coherent flag: the lanes are neighbouring pixels).
    fn intersect(&mut self, scene: &CommittedScene);
    /// After [`RayPacket::intersect`]: lane `k`'s nearest hit, or `None` for a miss or an
    /// inactive lane.
    fn hit(&self, k: usize) -> Option<PacketHit>;
}

mod private {
    pub trait Sealed {}
}

/// The `rtcInitIntersectContext` that Embree 3 defines inline (no symbol for bindgen).
#[cfg(not(feature = "embree4"))]
pub(super) fn intersect_context(coherent: bool) -> sys::RTCIntersectContext {
    sys::RTCIntersectContext {
        flags: if coherent {
            sys::RTCIntersectContextFlags::RTC_INTERSECT_CONTEXT_FLAG_COHERENT
        } else {
            sys::RTCIntersectContextFlags::RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT
        },
        filter: None,
        instID: [INVALID_GEOMETRY_ID; 1],
    }
}

/// Embree 4's coherent query arguments (`rtcInitIntersectArguments` is inline there).
#[cfg(feature = "embree4")]
fn coherent_arguments() -> sys::RTCIntersectArguments {
    let mut args = sys::RTCIntersectArguments::default();
    args.flags = sys::RTCRayQueryFlags::RTC_RAY_QUERY_FLAG_COHERENT;
    args.feature_mask = sys::RTCFeatureFlags::RTC_FEATURE_FLAG_ALL;
    args
}

macro_rules! packet {
    ($(#[$doc:meta])* $name:ident, $valid:ident, $align:literal, $lanes:literal, $rayhit:ident, $call:ident) => {
        /// The `valid` mask of the query (−1 = active), aligned as Embree requires.
        #[repr(C, align($align))]
        #[derive(Clone, Copy)]
        struct $valid([i32; $lanes]);

        $(#[$doc])*
        #[derive(Clone, Copy)]
        pub struct $name {
            valid: $valid,
            rh: sys::$rayhit,
        }

        impl private::Sealed for $name {}

        impl RayPacket for $name {
            const LANES: usize = $lanes;

            fn empty() -> Self {
                $name {
                    valid: $valid([0; $lanes]),
                    rh: sys::$rayhit::default(),
                }
            }

            #[inline]
            fn set_segment(&mut self, k: usize, org: [f32; 3], dir: [f32; 3], tnear: f32, tfar: f32) {
                self.valid.0[k] = -1;
                let r = &mut self.rh.ray;
                [r.org_x[k], r.org_y[k], r.org_z[k]] = org;
                [r.dir_x[k], r.dir_y[k], r.dir_z[k]] = dir;
                r.tnear[k] = tnear;
                r.tfar[k] = tfar;
                r.mask[k] = u32::MAX;
                self.rh.hit.geomID[k] = INVALID_GEOMETRY_ID;
                self.rh.hit.instID[0][k] = INVALID_GEOMETRY_ID;
            }

            #[inline]
            fn is_active(&self, k: usize) -> bool {
                self.valid.0[k] != 0
            }

            #[inline]
            fn any_active(&self) -> bool {
                self.valid.0.iter().any(|&v| v != 0)
            }

            #[inline]
            fn intersect(&mut self, scene: &CommittedScene) {
                if !self.any_active() {
                    return;
                }
                #[cfg(not(feature = "embree4"))]
                {
                    let mut ctx = intersect_context(true);
                    // SAFETY: `valid` and `rh` are aligned as their types say (Embree's
                    // `RTC_ALIGN`), valid and exclusively borrowed for the call; every
                    // active lane was fully written by `set`; the scene is live and
                    // committed (concurrent traversals allowed, see `CommittedScene`).
                    unsafe { sys::$call(self.valid.0.as_ptr(), scene.raw(), &mut ctx, &mut self.rh) };
                }
                #[cfg(feature = "embree4")]
                {
                    let mut args = coherent_arguments();
                    // SAFETY: as for Embree 3 above (not compiled or tested on Debian 12).
                    unsafe { sys::$call(self.valid.0.as_ptr(), scene.raw(), &mut self.rh, &mut args) };
                }
            }

            #[inline]
            fn hit(&self, k: usize) -> Option<PacketHit> {
                (self.valid.0[k] != 0 && self.rh.hit.geomID[k] != INVALID_GEOMETRY_ID).then(|| {
                    PacketHit {
                        t: self.rh.ray.tfar[k],
                        prim_id: self.rh.hit.primID[k],
                        geom_id: self.rh.hit.geomID[k],
                    }
                })
            }
        }
    };
}

packet!(
    /// 8 rays for `rtcIntersect8` (AVX2 width).
    Packet8, Valid8, 32, 8, RTCRayHit8, rtcIntersect8
);
packet!(
    /// 16 rays for `rtcIntersect16` (AVX-512 width).
    Packet16, Valid16, 64, 16, RTCRayHit16, rtcIntersect16
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_matches_embree() {
        assert_eq!(std::mem::align_of::<Valid8>(), 32);
        assert_eq!(std::mem::align_of::<Valid16>(), 64);
        assert!(std::mem::align_of::<sys::RTCRayHit8>() >= 32);
        assert!(std::mem::align_of::<sys::RTCRayHit16>() >= 64);
    }

    /// The lanes of each width (the tile shapes rest on them), and the native width against
    /// the kernel's flags (`/proc/cpuinfo`, not the `is_x86_feature_detected!` that
    /// [`PacketWidth::native`] asks) and Embree's own report of 16-wide support.
    #[test]
    fn native_width_follows_the_cpu() {
        assert_eq!((PacketWidth::W8.lanes(), PacketWidth::W16.lanes()), (8, 16));
        let dev = Device::new().unwrap();
        let Ok(cpuinfo) = std::fs::read_to_string("/proc/cpuinfo") else {
            return;
        };
        let avx512 = cpuinfo
            .lines()
            .filter(|l| l.starts_with("flags"))
            .any(|l| l.split_whitespace().any(|f| f == "avx512f"));
        // SAFETY: the device handle is live (held by `dev`); the property id is Embree's own.
        let ray16 = unsafe {
            sys::rtcGetDeviceProperty(
                dev.inner.raw(),
                sys::RTCDeviceProperty::RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED,
            )
        } == 1;
        let want = if avx512 && ray16 {
            PacketWidth::W16
        } else {
            PacketWidth::W8
        };
        assert_eq!(
            PacketWidth::native(&dev),
            want,
            "avx512f {avx512}, ray16 {ray16}"
        );
    }
}
