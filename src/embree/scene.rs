//! Embree scenes: [`Scene`] (being built, owns its geometry buffers) and
//! [`CommittedScene`] (read-only, `Send + Sync`, the only thing that can be queried), plus
//! the single-ray query (packets: `packet.rs`).
use std::ptr::NonNull;
use std::sync::Arc;

use super::device::{Device, DeviceInner, EmbreeError};
use super::sys;

/// `RTC_INVALID_GEOMETRY_ID` (`(unsigned)-1`); bindgen does not emit this macro.
const INVALID_GEOMETRY_ID: u32 = u32::MAX;

/// A ray hit, in our own terms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the ray direction (in units of the direction's length).
    pub t: f32,
    /// Triangle index within its geometry.
    pub prim_id: u32,
    /// Geometry id (the order `add_triangles` was called in, from 0).
    pub geom_id: u32,
    /// Barycentric coordinates of the hit.
    pub u: f32,
    pub v: f32,
    /// Unnormalised geometric normal.
    pub ng: [f32; 3],
}

/// Triangle buffers shared with Embree. The vertex buffer carries one extra (zero) vertex:
/// Embree may load 16 bytes from the last FLOAT3, i.e. 4 bytes past its end.
struct Buffers {
    vertices: Vec<[f32; 3]>,
    faces: Vec<[u32; 3]>,
}

/// A scene under construction (RAII over `RTCScene`).
pub struct Scene {
    raw: NonNull<sys::RTCSceneTy>,
    device: Arc<DeviceInner>,
    buffers: Vec<Buffers>,
}

impl Drop for Scene {
    fn drop(&mut self) {
        // SAFETY: `raw` came from rtcNewScene and is owned only by this value.
        unsafe { sys::rtcReleaseScene(self.raw.as_ptr()) };
    }
}

impl Scene {
    /// An empty scene on `device` (robust traversal off, default build quality).
    pub fn new(device: &Device) -> Result<Scene, EmbreeError> {
        let dev = device.inner.clone();
        // SAFETY: the device handle is live (held by `dev`).
        let raw = unsafe { sys::rtcNewScene(dev.raw()) };
        let Some(raw) = NonNull::new(raw) else {
            dev.check("rtcNewScene")?;
            return Err(EmbreeError::Call {
                during: "rtcNewScene",
                code: "null scene".into(),
                message: String::new(),
            });
        };
        Ok(Scene {
            raw,
            device: dev,
            buffers: Vec::new(),
        })
    }

    /// Adds a triangle mesh; returns its geometry id. Indices and coordinates are checked
    /// first (Embree would read out of bounds on a bad index). An empty mesh adds nothing
    /// and returns `None`.
    pub fn add_triangles(
        &mut self,
        vertices: &[[f32; 3]],
        faces: &[[u32; 3]],
    ) -> Result<Option<u32>, EmbreeError> {
        if faces.is_empty() {
            return Ok(None);
        }
        if vertices.len() >= u32::MAX as usize || faces.len() >= u32::MAX as usize {
            return Err(EmbreeError::InvalidMesh(
                "more than 2³²−2 vertices or faces".into(),
            ));
        }
        let n = vertices.len() as u32;
        if let Some((i, f)) = faces
            .iter()
            .enumerate()
            .find(|(_, f)| f.iter().any(|&v| v >= n))
        {
            return Err(EmbreeError::InvalidMesh(format!(
                "face {i} {f:?} references a vertex ≥ {n}"
            )));
        }
        if let Some(i) = vertices
            .iter()
            .position(|v| v.iter().any(|c| !c.is_finite()))
        {
            return Err(EmbreeError::InvalidMesh(format!(
                "vertex {i} is not finite"
            )));
        }
        let mut verts = Vec::with_capacity(vertices.len() + 1);
        verts.extend_from_slice(vertices);
        verts.push([0.0; 3]); // padding, see `Buffers`
        let buf = Buffers {
            vertices: verts,
            faces: faces.to_vec(),
        };
        // SAFETY: the device is live; TRIANGLE is a valid geometry type.
        let geom = unsafe {
            sys::rtcNewGeometry(
                self.device.raw(),
                sys::RTCGeometryType::RTC_GEOMETRY_TYPE_TRIANGLE,
            )
        };
        if geom.is_null() {
            self.device.check("rtcNewGeometry")?;
            return Err(EmbreeError::Call {
                during: "rtcNewGeometry",
                code: "null geometry".into(),
                message: String::new(),
            });
        }
        // SAFETY: `geom` is a live triangle geometry. The shared buffers point into
        // `buf`'s heap allocations, which are moved (not reallocated) into `self.buffers`
        // and stay alive and unmodified until the scene — the last user of the geometry —
        // is released (the scene, committed or not, owns them). Strides and counts match
        // the Vec layouts ([f32;3] = 12 bytes, [u32;3] = 12 bytes); the vertex allocation
        // has one padding vertex beyond `vertices.len()` items. After attaching,
        // our geometry reference is released (the scene keeps its own).
        let id = unsafe {
            sys::rtcSetSharedGeometryBuffer(
                geom,
                sys::RTCBufferType::RTC_BUFFER_TYPE_VERTEX,
                0,
                sys::RTCFormat::RTC_FORMAT_FLOAT3,
                buf.vertices.as_ptr().cast(),
                0,
                12,
                vertices.len(),
            );
            sys::rtcSetSharedGeometryBuffer(
                geom,
                sys::RTCBufferType::RTC_BUFFER_TYPE_INDEX,
                0,
                sys::RTCFormat::RTC_FORMAT_UINT3,
                buf.faces.as_ptr().cast(),
                0,
                12,
                faces.len(),
            );
            sys::rtcCommitGeometry(geom);
            let id = sys::rtcAttachGeometry(self.raw.as_ptr(), geom);
            sys::rtcReleaseGeometry(geom);
            id
        };
        // The buffers are pushed before any early return: Embree shares them.
        self.buffers.push(buf);
        self.device.check("adding triangles")?;
        // Geometry ids of a scene that never detaches are 0, 1, 2, … in attach order; the
        // point query looks the triangles up by id, so the two must agree.
        if id as usize + 1 != self.buffers.len() {
            return Err(EmbreeError::Call {
                during: "rtcAttachGeometry",
                code: format!("unexpected geometry id {id}"),
                message: format!("expected {}", self.buffers.len() - 1),
            });
        }
        Ok(Some(id))
    }

    /// Asks for Embree's high-quality BVH build (`RTC_BUILD_QUALITY_HIGH`: SAH with
    /// spatial splits) instead of the default medium one: slower to build, meant for a
    /// static scene (the default `RTC_SCENE_FLAG_NONE`: no dynamic updates) traced often.
    pub fn set_high_quality(&mut self) -> Result<(), EmbreeError> {
        // SAFETY: `raw` is live and uncommitted; HIGH is a valid build quality.
        unsafe {
            sys::rtcSetSceneBuildQuality(
                self.raw.as_ptr(),
                sys::RTCBuildQuality::RTC_BUILD_QUALITY_HIGH,
            )
        };
        self.device.check("rtcSetSceneBuildQuality")
    }

    /// Builds the BVH; only a committed scene can be queried.
    pub fn commit(self) -> Result<CommittedScene, EmbreeError> {
        // SAFETY: `raw` is live and no other thread can reach an uncommitted `Scene`
        // (`Scene` is neither Send nor Sync: it holds a raw pointer).
        unsafe { sys::rtcCommitScene(self.raw.as_ptr()) };
        self.device.check("rtcCommitScene")?;
        Ok(CommittedScene { scene: self })
    }
}

/// A geometry's vertices and faces, as shared with Embree.
pub(super) type TriangleBuffers<'a> = (&'a [[f32; 3]], &'a [[u32; 3]]);

/// A committed, read-only scene: the only thing rays can be cast into.
pub struct CommittedScene {
    scene: Scene,
}

// SAFETY: after `rtcCommitScene` the scene is never modified again (CommittedScene exposes
// no mutating call and owns the buffers it shares with Embree, which nothing else can
// reach). Embree documents that a committed scene may be traced from any number of
// threads concurrently (rtcCommitScene man page; RenderKit/embree#207) and the device is
// thread-safe, so moving the handle to another thread or sharing `&CommittedScene`
// between threads is sound.
unsafe impl Send for CommittedScene {}
// SAFETY: see `Send` above: every `&self` method only issues concurrent-safe traversal calls.
unsafe impl Sync for CommittedScene {}

/// One ray query (Embree 3 signature).
#[cfg(not(feature = "embree4"))]
fn raw_intersect1(scene: sys::RTCScene, rh: &mut sys::RTCRayHit) {
    let mut ctx = super::packet::intersect_context(false);
    // SAFETY: `scene` is a live committed scene; `ctx` and `rh` are valid, aligned,
    // exclusively borrowed for the call.
    unsafe { sys::rtcIntersect1(scene, &mut ctx, rh) };
}

/// One ray query (Embree 4 signature; not compiled or tested on Debian 12).
#[cfg(feature = "embree4")]
fn raw_intersect1(scene: sys::RTCScene, rh: &mut sys::RTCRayHit) {
    // SAFETY: a null RTCIntersectArguments selects Embree 4's defaults (incoherent).
    unsafe { sys::rtcIntersect1(scene, rh, std::ptr::null_mut()) };
}

impl CommittedScene {
    pub(super) fn raw(&self) -> sys::RTCScene {
        self.scene.raw.as_ptr()
    }

    /// Vertices (without the padding vertex) and faces of geometry `geom_id`.
    pub(super) fn triangles(&self, geom_id: u32) -> Option<TriangleBuffers<'_>> {
        self.scene.buffers.get(geom_id as usize).map(|b| {
            (
                &b.vertices[..b.vertices.len().saturating_sub(1)],
                &b.faces[..],
            )
        })
    }

    /// Nearest hit of the ray `org + t·dir`, `t ∈ [0, tfar]`.
    pub fn intersect1(&self, org: [f32; 3], dir: [f32; 3], tfar: f32) -> Option<Hit> {
        let mut rh = sys::RTCRayHit {
            ray: sys::RTCRay {
                org_x: org[0],
                org_y: org[1],
                org_z: org[2],
                tnear: 0.0,
                dir_x: dir[0],
                dir_y: dir[1],
                dir_z: dir[2],
                time: 0.0,
                tfar,
                mask: u32::MAX,
                id: 0,
                flags: 0,
            },
            hit: sys::RTCHit {
                geomID: INVALID_GEOMETRY_ID,
                instID: [INVALID_GEOMETRY_ID],
                ..Default::default()
            },
        };
        raw_intersect1(self.raw(), &mut rh);
        (rh.hit.geomID != INVALID_GEOMETRY_ID).then_some(Hit {
            t: rh.ray.tfar,
            prim_id: rh.hit.primID,
            geom_id: rh.hit.geomID,
            u: rh.hit.u,
            v: rh.hit.v,
            ng: [rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::embree::{Packet8, Packet16, RayPacket};

    fn quad_scene() -> CommittedScene {
        let dev = Device::new().unwrap();
        let mut s = Scene::new(&dev).unwrap();
        // Unit square at z = 2 (two triangles), then a second geometry at z = 5.
        let v = [
            [0.0, 0.0, 2.0],
            [1.0, 0.0, 2.0],
            [1.0, 1.0, 2.0],
            [0.0, 1.0, 2.0],
        ];
        assert_eq!(
            s.add_triangles(&v, &[[0, 1, 2], [0, 2, 3]]).unwrap(),
            Some(0)
        );
        let w = v.map(|p| [p[0] - 0.5, p[1], 5.0]);
        assert_eq!(
            s.add_triangles(&w, &[[0, 1, 2], [0, 2, 3]]).unwrap(),
            Some(1)
        );
        drop(dev); // scenes keep the device alive
        s.commit().unwrap()
    }

    /// Whether Embree's distance `t` is `want` within 4 ulp: its kernels for each instruction
    /// set (SSE, AVX2, AVX-512; single rays and packets) may differ in the last bits (the AVX2
    /// `rtcIntersect1` gives 1.9999999 for the plane z = 2 seen from z = 0).
    fn near(t: f32, want: f32) -> bool {
        (t - want).abs() <= 4.0 * f32::EPSILON * want.abs()
    }

    #[test]
    fn intersect1_and_packets_agree() {
        let sc = quad_scene();
        let h = sc
            .intersect1([0.75, 0.25, 0.0], [0.0, 0.0, 1.0], f32::INFINITY)
            .unwrap();
        assert_eq!((h.prim_id, h.geom_id), (0, 0));
        assert!(near(h.t, 2.0), "{}", h.t);
        let h = sc
            .intersect1([0.25, 0.75, 0.0], [0.0, 0.0, 1.0], f32::INFINITY)
            .unwrap();
        assert_eq!((h.prim_id, h.geom_id), (1, 0));
        assert!(near(h.t, 2.0), "{}", h.t);
        let h = sc
            .intersect1([-0.25, 0.5, 0.0], [0.0, 0.0, 1.0], f32::INFINITY)
            .unwrap();
        assert_eq!(h.geom_id, 1);
        assert!(near(h.t, 5.0), "{}", h.t);
        assert!(
            sc.intersect1([-0.25, 0.5, 0.0], [0.0, 0.0, 1.0], 4.0)
                .is_none()
        );
        assert!(
            sc.intersect1([3.0, 3.0, 0.0], [0.0, 0.0, 1.0], f32::INFINITY)
                .is_none()
        );

        fn lanes<P: RayPacket>(sc: &CommittedScene) {
            let mut p = P::empty();
            let dir = [0.0, 0.0, 1.0];
            let org = |i: usize| [-0.6 + 0.1 * i as f32, 0.3 + 0.01 * i as f32, 0.0];
            for i in 0..P::LANES {
                if i != 7 {
                    p.set(i, org(i), dir, f32::INFINITY);
                }
            }
            assert!(!p.is_active(7) && p.is_active(0));
            p.intersect(sc);
            let mut hits = 0;
            for i in 0..P::LANES {
                let single = sc.intersect1(org(i), dir, f32::INFINITY);
                if i == 7 {
                    assert!(p.hit(i).is_none());
                } else {
                    hits += usize::from(p.hit(i).is_some());
                    let (got, want) = (p.hit(i), single);
                    assert_eq!(
                        got.map(|h| (h.geom_id, h.prim_id)),
                        want.map(|h| (h.geom_id, h.prim_id)),
                        "lane {i} of {}",
                        P::LANES
                    );
                    if let (Some(a), Some(b)) = (got, want) {
                        assert!(near(a.t, b.t), "lane {i}: {} vs {}", a.t, b.t);
                    }
                }
            }
            assert!(hits >= P::LANES / 2 + 2);
        }
        lanes::<Packet8>(&sc);
        lanes::<Packet16>(&sc);
    }

    #[test]
    fn bad_meshes_are_errors_and_empty_scenes_miss() {
        let dev = Device::new().unwrap();
        let mut s = Scene::new(&dev).unwrap();
        assert!(matches!(
            s.add_triangles(&[[0.0; 3]; 3], &[[0, 1, 3]]),
            Err(EmbreeError::InvalidMesh(_))
        ));
        assert!(matches!(
            s.add_triangles(&[[0.0, 0.0, f32::NAN], [1.0; 3], [2.0; 3]], &[[0, 1, 2]]),
            Err(EmbreeError::InvalidMesh(_))
        ));
        assert_eq!(s.add_triangles(&[], &[]).unwrap(), None);
        let c = s.commit().unwrap();
        assert!(
            c.intersect1([0.0; 3], [0.0, 0.0, 1.0], f32::INFINITY)
                .is_none()
        );
        let mut p = Packet16::empty();
        for k in 0..16 {
            p.set(k, [k as f32, 0.0, 0.0], [0.0, 0.0, 1.0], f32::INFINITY);
        }
        p.intersect(&c);
        assert!((0..16).all(|k| p.hit(k).is_none()));
    }

    #[test]
    fn committed_scene_is_send_and_sync() {
        fn assert_send_sync<T: Send + Sync>() {}
        assert_send_sync::<CommittedScene>();
        assert_send_sync::<Device>();
    }
}
