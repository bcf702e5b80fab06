//! Simulated cameras in the local metric frame: oblique drone orbits around the buildings
//! (round-robin over buildings, golden-angle azimuths, radius and pitch drawn from the
//! configured ranges) and street-level views in front of walls. PINHOLE, one shared camera.
use glam::DVec3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::city::CityInfo;
use super::config::Cameras;
use super::world::GroundMap;
use crate::camera::{Camera, Distortion, Intrinsics, Pose};

/// A camera before naming: its kind (`orbit`/`street`) and pose in the local frame.
#[derive(Debug, Clone)]
pub struct SimCamera {
    pub kind: &'static str,
    pub camera: Camera,
}

pub fn intrinsics(c: &Cameras) -> Intrinsics {
    let fx = f64::from(c.width) * 0.5 / (c.hfov_deg.to_radians() * 0.5).tan();
    Intrinsics {
        width: c.width,
        height: c.height,
        fx,
        fy: fx * c.pixel_aspect,
        cx: f64::from(c.width) * 0.5,
        cy: f64::from(c.height) * 0.5,
        distortion: Distortion::None,
    }
}

pub fn generate(
    cfg: &Cameras,
    city: &CityInfo,
    map: &GroundMap,
    rng: &mut ChaCha8Rng,
) -> Vec<SimCamera> {
    let k = intrinsics(cfg);
    let mut out = Vec::new();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let nb = city.buildings.len().max(1);
    for i in 0..cfg.orbit_views {
        let target = match city.buildings.get(i % nb) {
            Some(b) => {
                let c = (b.lo + b.hi) * 0.5;
                DVec3::new(c.x, c.y, b.lo.z + (b.hi.z - b.lo.z) * 0.4)
            }
            None => DVec3::ZERO,
        };
        let az = i as f64 * golden + rng.random::<f64>() * 0.2;
        let r = lerp(cfg.orbit_radius, rng.random::<f64>());
        let pitch = lerp(cfg.orbit_pitch_deg, rng.random::<f64>()).to_radians();
        let eye = target + DVec3::new(az.cos() * r, az.sin() * r, r * pitch.tan());
        if let Some(pose) = Pose::look_at(eye, target, DVec3::Z) {
            out.push(SimCamera {
                kind: "orbit",
                camera: Camera {
                    intrinsics: k,
                    pose,
                },
            });
        }
    }
    // Street level: in front of walls with openings (area-weighted; all walls when none has
    // openings), where the ground is free.
    let with_openings: std::collections::BTreeSet<i32> =
        city.openings.iter().map(|o| o.surface).collect();
    let walls: Vec<&super::city::Facet> =
        if city.walls.iter().any(|w| with_openings.contains(&w.entity)) {
            city.walls
                .iter()
                .filter(|w| with_openings.contains(&w.entity))
                .collect()
        } else {
            city.walls.iter().collect()
        };
    let total: f64 = walls.iter().map(|w| w.area).sum();
    let mut made = 0;
    let mut tries = 0;
    while made < cfg.street_views && tries < cfg.street_views * 50 && total > 0.0 {
        tries += 1;
        let mut pick = rng.random::<f64>() * total;
        let mut wall = walls[0];
        for w in &walls {
            wall = w;
            if pick < w.area {
                break;
            }
            pick -= w.area;
        }
        let nh = DVec3::new(wall.normal.x, wall.normal.y, 0.0).normalize_or_zero();
        if nh == DVec3::ZERO {
            continue;
        }
        let d = lerp(cfg.street_distance, rng.random::<f64>());
        let yaw = (rng.random::<f64>() - 0.5) * 0.8;
        let dir = DVec3::new(
            nh.x * yaw.cos() - nh.y * yaw.sin(),
            nh.x * yaw.sin() + nh.y * yaw.cos(),
            0.0,
        );
        let foot = wall.centroid + dir * d;
        // Free line of sight on the ground: every 0.5 m from 1.5 m off the wall.
        let mut free = true;
        let mut s = 1.5;
        while s <= d {
            let q = wall.centroid + dir * s;
            if map.distance(q.x, q.y).is_none_or(|g| g < 0.6) {
                free = false;
                break;
            }
            s += 0.5;
        }
        if !free {
            continue;
        }
        let gz = map.height(foot.x, foot.y);
        let eye = DVec3::new(foot.x, foot.y, gz + cfg.street_height);
        let target = DVec3::new(
            wall.centroid.x,
            wall.centroid.y,
            gz + cfg.street_height + 3.0,
        );
        if let Some(pose) = Pose::look_at(eye, target, DVec3::Z) {
            out.push(SimCamera {
                kind: "street",
                camera: Camera {
                    intrinsics: k,
                    pose,
                },
            });
            made += 1;
        }
    }
    out
}

fn lerp(r: [f64; 2], t: f64) -> f64 {
    r[0] + (r[1] - r[0]) * t
}
