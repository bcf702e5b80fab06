//! The simulated world around the buildings: a ground map (footprint raster, distance to the
//! nearest building, ground height), ground Gaussians (pavement, road, grass), a water patch,
//! objects the city model does not know (trees, cars, persons — some placed in front of
//! windows/doors as occluders) and floaters. All in the local metric frame.
use glam::{DMat3, DVec3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::city::{CityInfo, Facet, palette};
use super::config::{Ground, Objects, Splats};
use super::gaussians::{Builder, Splat, frame_from_normal, value_noise};
use crate::classes;

/// First instance id of simulated non-city instances.
pub const FIRST_INSTANCE: i32 = 1_000_000;
pub const ROAD_INSTANCE: i32 = FIRST_INSTANCE;
pub const PAVEMENT_INSTANCE: i32 = FIRST_INSTANCE + 1;
pub const GRASS_INSTANCE: i32 = FIRST_INSTANCE + 2;
pub const WATER_INSTANCE: i32 = FIRST_INSTANCE + 3;
pub const FLOATER_INSTANCE: i32 = FIRST_INSTANCE + 4;
/// Objects (trees, cars, persons) count up from here.
pub const FIRST_OBJECT: i32 = FIRST_INSTANCE + 10;

const CELL: f64 = 0.5;

/// Raster of the ground area: distance to the nearest building footprint and ground height.
#[derive(Debug, Clone)]
pub struct GroundMap {
    pub lo: [f64; 2],
    pub nx: usize,
    pub ny: usize,
    /// Metres to the nearest footprint cell (0 inside).
    pub dist: Vec<f32>,
    /// Building bases `(x, y, z)` for the inverse-distance height.
    bases: Vec<DVec3>,
    pub zmax: f64,
}

impl GroundMap {
    pub fn new(city: &CityInfo, margin: f64) -> GroundMap {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for b in &city.buildings {
            lo = lo.min(b.lo);
            hi = hi.max(b.hi);
        }
        if !lo.is_finite() {
            lo = DVec3::ZERO;
            hi = DVec3::ZERO;
        }
        let lo2 = [lo.x - margin, lo.y - margin];
        let nx = (((hi.x - lo.x + 2.0 * margin) / CELL).ceil() as usize).max(1);
        let ny = (((hi.y - lo.y + 2.0 * margin) / CELL).ceil() as usize).max(1);
        let big = 1e9f32;
        let mut dist = vec![big; nx * ny];
        for t in &city.triangles {
            let (a, b, c) = (t[0], t[1], t[2]);
            let x0 = ((a.x.min(b.x).min(c.x) - lo2[0]) / CELL).floor().max(0.0) as usize;
            let x1 = (((a.x.max(b.x).max(c.x) - lo2[0]) / CELL).ceil() as usize).min(nx - 1);
            let y0 = ((a.y.min(b.y).min(c.y) - lo2[1]) / CELL).floor().max(0.0) as usize;
            let y1 = (((a.y.max(b.y).max(c.y) - lo2[1]) / CELL).ceil() as usize).min(ny - 1);
            let d = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let px = lo2[0] + (x as f64 + 0.5) * CELL;
                    let py = lo2[1] + (y as f64 + 0.5) * CELL;
                    let inside = if d.abs() < 1e-9 {
                        // Vertical triangle: mark cells its edges cross (within half a cell).
                        seg_dist(px, py, a, b) < CELL * 0.5
                            || seg_dist(px, py, b, c) < CELL * 0.5
                            || seg_dist(px, py, c, a) < CELL * 0.5
                    } else {
                        let w0 = ((b.x - px) * (c.y - py) - (c.x - px) * (b.y - py)) / d;
                        let w1 = ((c.x - px) * (a.y - py) - (a.x - px) * (c.y - py)) / d;
                        let w2 = 1.0 - w0 - w1;
                        w0 >= -0.05 && w1 >= -0.05 && w2 >= -0.05
                    };
                    if inside {
                        dist[y * nx + x] = 0.0;
                    }
                }
            }
        }
        // Two-pass chamfer distance (1, √2).
        let s2 = std::f32::consts::SQRT_2;
        for y in 0..ny {
            for x in 0..nx {
                let mut v = dist[y * nx + x];
                if x > 0 {
                    v = v.min(dist[y * nx + x - 1] + 1.0);
                }
                if y > 0 {
                    v = v.min(dist[(y - 1) * nx + x] + 1.0);
                    if x > 0 {
                        v = v.min(dist[(y - 1) * nx + x - 1] + s2);
                    }
                    if x + 1 < nx {
                        v = v.min(dist[(y - 1) * nx + x + 1] + s2);
                    }
                }
                dist[y * nx + x] = v;
            }
        }
        for y in (0..ny).rev() {
            for x in (0..nx).rev() {
                let mut v = dist[y * nx + x];
                if x + 1 < nx {
                    v = v.min(dist[y * nx + x + 1] + 1.0);
                }
                if y + 1 < ny {
                    v = v.min(dist[(y + 1) * nx + x] + 1.0);
                    if x + 1 < nx {
                        v = v.min(dist[(y + 1) * nx + x + 1] + s2);
                    }
                    if x > 0 {
                        v = v.min(dist[(y + 1) * nx + x - 1] + s2);
                    }
                }
                dist[y * nx + x] = v;
            }
        }
        for d in &mut dist {
            *d *= CELL as f32;
        }
        let bases = city
            .buildings
            .iter()
            .map(|b| DVec3::new((b.lo.x + b.hi.x) * 0.5, (b.lo.y + b.hi.y) * 0.5, b.lo.z))
            .collect();
        GroundMap {
            lo: lo2,
            nx,
            ny,
            dist,
            bases,
            zmax: hi.z,
        }
    }

    pub fn extent(&self) -> ([f64; 2], [f64; 2]) {
        (
            self.lo,
            [
                self.lo[0] + self.nx as f64 * CELL,
                self.lo[1] + self.ny as f64 * CELL,
            ],
        )
    }

    /// Distance to the nearest building (metres); `None` outside the map.
    pub fn distance(&self, x: f64, y: f64) -> Option<f64> {
        let cx = ((x - self.lo[0]) / CELL).floor();
        let cy = ((y - self.lo[1]) / CELL).floor();
        if cx < 0.0 || cy < 0.0 || cx >= self.nx as f64 || cy >= self.ny as f64 {
            return None;
        }
        Some(f64::from(self.dist[cy as usize * self.nx + cx as usize]))
    }

    /// Ground height: inverse-distance-weighted building base heights.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let (mut sw, mut sz) = (0.0, 0.0);
        for b in &self.bases {
            let d2 = (b.x - x).powi(2) + (b.y - y).powi(2) + 1.0;
            let w = 1.0 / (d2 * d2);
            sw += w;
            sz += w * b.z;
        }
        if sw > 0.0 { sz / sw } else { 0.0 }
    }
}

fn seg_dist(px: f64, py: f64, a: DVec3, b: DVec3) -> f64 {
    let (dx, dy) = (b.x - a.x, b.y - a.y);
    let l2 = dx * dx + dy * dy;
    let t = if l2 > 0.0 {
        (((px - a.x) * dx + (py - a.y) * dy) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    ((a.x + t * dx - px).powi(2) + (a.y + t * dy - py).powi(2)).sqrt()
}

/// A simulated object the city model does not know.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectInfo {
    pub instance: i32,
    pub class: &'static str,
    /// Base point (local metric frame, metres).
    pub position: [f64; 3],
    /// The window/door entity it was placed in front of, if it is an occluder.
    pub occludes: Option<i32>,
    pub gaussians: usize,
    /// The solids its Gaussians' centres were drawn in (local metric frame), from the object's
    /// own parameters (not from its Gaussians): every centre lies in one of them.
    pub shapes: Vec<Shape>,
}

/// A solid an object's Gaussian centres were drawn in (local metric frame, metres).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// An oriented box: `centre`, its unit axes (rows) and the half extents along them.
    Box {
        centre: [f64; 3],
        axes: [[f64; 3]; 3],
        half: [f64; 3],
    },
    /// A ball.
    Sphere { centre: [f64; 3], radius: f64 },
}

impl Shape {
    /// The box `lo..hi` of a local frame (columns of `frame`) placed at `origin`.
    fn framed_box(origin: DVec3, frame: DMat3, lo: DVec3, hi: DVec3) -> Shape {
        Shape::Box {
            centre: (origin + frame * ((lo + hi) * 0.5)).to_array(),
            axes: [frame.x_axis, frame.y_axis, frame.z_axis].map(|a| a.to_array()),
            half: ((hi - lo) * 0.5).to_array(),
        }
    }
}

/// Ground, water, objects, floaters.
#[derive(Debug, Default, Serialize)]
pub struct WorldInfo {
    pub objects: Vec<ObjectInfo>,
    pub water: bool,
    pub floaters: usize,
}

fn truth(class: i32, instance: i32) -> [i32; 5] {
    [class, instance, -1, -1, -1]
}

fn jitter(rng: &mut ChaCha8Rng, c: [f64; 3], s: f64) -> [f64; 3] {
    c.map(|v| v + (rng.random::<f64>() - 0.5) * 2.0 * s)
}

/// Ground Gaussians (pavement, road, grass, water).
pub fn ground(
    map: &GroundMap,
    cfg: &Ground,
    splats: &Splats,
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) -> bool {
    if cfg.density <= 0.0 {
        return false;
    }
    let (lo, hi) = map.extent();
    // Water: the cell farthest from any building whose whole disc lies inside the ground
    // extent (otherwise most of the patch would fall off the map), if there is room.
    let r = cfg.water_radius;
    let mut best = (0.0f32, 0usize);
    for (i, &d) in map.dist.iter().enumerate() {
        let cx = lo[0] + ((i % map.nx) as f64 + 0.5) * CELL;
        let cy = lo[1] + ((i / map.nx) as f64 + 0.5) * CELL;
        let inside = cx - lo[0] >= r && hi[0] - cx >= r && cy - lo[1] >= r && hi[1] - cy >= r;
        if inside && d > best.0 {
            best = (d, i);
        }
    }
    let water_c = DVec3::new(
        lo[0] + ((best.1 % map.nx) as f64 + 0.5) * CELL,
        lo[1] + ((best.1 / map.nx) as f64 + 0.5) * CELL,
        0.0,
    );
    let water = cfg.water_radius > 0.0 && f64::from(best.0) > cfg.water_radius + 1.0;
    let area = (hi[0] - lo[0]) * (hi[1] - lo[1]);
    let n = (area * cfg.density).round() as usize;
    let spacing = 1.0 / cfg.density.sqrt();
    let sigma = spacing * splats.scale_factor;
    let up = frame_from_normal(DVec3::Z);
    for _ in 0..n {
        let x = lo[0] + rng.random::<f64>() * (hi[0] - lo[0]);
        let y = lo[1] + rng.random::<f64>() * (hi[1] - lo[1]);
        let d = map.distance(x, y).unwrap_or(f64::MAX);
        let jit = rng.random::<f64>() - 0.5;
        if d < 0.01 {
            continue; // under a building
        }
        let z = map.height(x, y);
        let p = DVec3::new(x, y, z);
        let in_water =
            water && (p - DVec3::new(water_c.x, water_c.y, z)).length() < cfg.water_radius;
        let (class, inst, rgb, reflect, dz) = if in_water {
            let c = palette(classes::WATER);
            let nz = value_noise(p, 0.8, 5) * 0.05;
            (
                classes::WATER,
                WATER_INSTANCE,
                c.map(|v| v + nz),
                Some((DVec3::Z, [0.25, 0.3, 0.35])),
                -0.05,
            )
        } else if d < cfg.pavement_width {
            // Pavement: light slabs with joints.
            let joint = ((x / 0.6).fract().abs() < 0.06) || ((y / 0.6).fract().abs() < 0.06);
            let base = if joint { 0.52 } else { 0.66 };
            let nz = value_noise(p, 2.0, 6) * 0.05;
            (
                classes::ROAD,
                PAVEMENT_INSTANCE,
                [base + nz, base + nz, base * 0.97 + nz],
                None,
                0.12,
            )
        } else if d < cfg.pavement_width + cfg.road_width {
            let c = palette(classes::ROAD);
            let nz = value_noise(p, 1.5, 7) * 0.04 + jit * 0.04;
            (classes::ROAD, ROAD_INSTANCE, c.map(|v| v + nz), None, 0.0)
        } else {
            let nz = value_noise(p, 3.0, 8) * 0.08 + jit * 0.06;
            (
                classes::ROAD,
                GRASS_INSTANCE,
                [0.30 + nz, 0.50 + nz, 0.20 + nz * 0.5],
                None,
                0.02,
            )
        };
        out.push(Splat {
            pos: p + DVec3::Z * dz,
            frame: up,
            sigma: [sigma, sigma, splats.thickness],
            rgb,
            opacity: splats.opacity,
            reflect,
            truth: truth(class, inst),
        });
    }
    water
}

/// A free place for an object of clearance `r` in front of `f` (or anywhere when `None`).
fn place(
    map: &GroundMap,
    f: Option<&Facet>,
    dist: f64,
    r: f64,
    rng: &mut ChaCha8Rng,
) -> Option<DVec3> {
    if let Some(f) = f {
        let nh = DVec3::new(f.normal.x, f.normal.y, 0.0).try_normalize()?;
        let mut d = dist;
        while d < dist + 8.0 {
            let p = f.centroid + nh * d;
            if map.distance(p.x, p.y).is_some_and(|g| g >= r) {
                return Some(DVec3::new(p.x, p.y, map.height(p.x, p.y)));
            }
            d += 0.5;
        }
        return None;
    }
    let (lo, hi) = map.extent();
    for _ in 0..400 {
        let x = lo[0] + rng.random::<f64>() * (hi[0] - lo[0]);
        let y = lo[1] + rng.random::<f64>() * (hi[1] - lo[1]);
        if map.distance(x, y).is_some_and(|g| g >= r + 0.5) {
            return Some(DVec3::new(x, y, map.height(x, y)));
        }
    }
    None
}

/// Trees, cars, persons (a fraction placed in front of openings) and floaters.
pub fn objects(
    map: &GroundMap,
    city: &CityInfo,
    cfg: &Objects,
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) -> WorldInfo {
    let mut info = WorldInfo::default();
    let mut next = FIRST_OBJECT;
    // Openings near the ground, largest first (ties by entity id): candidates for occluders.
    let mut low: Vec<&Facet> = city
        .openings
        .iter()
        .filter(|f| f.normal.z.abs() < 0.5)
        .filter(|f| map.distance(f.centroid.x, f.centroid.y).is_some())
        .filter(|f| f.centroid.z - map.height(f.centroid.x, f.centroid.y) < 7.0)
        .collect();
    low.sort_by(|a, b| {
        let ha = a.centroid.z - map.height(a.centroid.x, a.centroid.y);
        let hb = b.centroid.z - map.height(b.centroid.x, b.centroid.y);
        ha.total_cmp(&hb).then(a.entity.cmp(&b.entity))
    });
    let doors: Vec<&Facet> = low
        .iter()
        .copied()
        .filter(|f| f.class == classes::DOOR)
        .collect();
    let mut used = std::collections::BTreeSet::new();
    let mut pick = |pool: &[&Facet], rng: &mut ChaCha8Rng| -> Option<Facet> {
        let free: Vec<&&Facet> = pool.iter().filter(|f| !used.contains(&f.entity)).collect();
        if free.is_empty() {
            return None;
        }
        // Prefer low openings: choose among the lowest third.
        let k = rng.random_range(0..free.len().div_ceil(3).max(1));
        used.insert(free[k].entity);
        Some((*free[k]).clone())
    };
    let kinds = [
        (classes::TREE, cfg.trees),
        (classes::CAR, cfg.cars),
        (classes::PERSON, cfg.persons),
    ];
    for (class, count) in kinds {
        let n_occ = (count as f64 * cfg.occluder_fraction).round() as usize;
        for k in 0..count {
            let (clear, dist) = match class {
                classes::TREE => (2.0, 3.5),
                classes::CAR => (1.3, 2.5),
                _ => (0.5, 1.2),
            };
            let facet = if k < n_occ {
                let pool: &[&Facet] = if class == classes::PERSON && !doors.is_empty() {
                    &doors
                } else {
                    &low
                };
                pick(pool, rng)
            } else {
                None
            };
            let Some(base) = place(map, facet.as_ref(), dist, clear, rng) else {
                continue;
            };
            let inst = next;
            next += 1;
            let before = out.len();
            let facing = facet.as_ref().map(|f| f.normal).unwrap_or_else(|| {
                let a = rng.random::<f64>() * std::f64::consts::TAU;
                DVec3::new(a.cos(), a.sin(), 0.0)
            });
            let shapes = match class {
                classes::TREE => tree(base, cfg.tree_gaussians, inst, rng, out),
                classes::CAR => car(base, facing, inst, rng, out),
                _ => person(base, inst, rng, out),
            };
            info.objects.push(ObjectInfo {
                instance: inst,
                class: classes::name(class),
                position: base.to_array(),
                occludes: facet.map(|f| f.entity),
                gaussians: out.len() - before,
                shapes,
            });
        }
    }
    // Floaters.
    let n_float = (out.len() as f64 * cfg.floater_fraction).round() as usize;
    let (lo, hi) = map.extent();
    for _ in 0..n_float {
        let p = DVec3::new(
            lo[0] + rng.random::<f64>() * (hi[0] - lo[0]),
            lo[1] + rng.random::<f64>() * (hi[1] - lo[1]),
            2.0 + rng.random::<f64>() * (map.zmax + 8.0),
        );
        let s = 0.05 + rng.random::<f64>() * 0.25;
        let rgb = [
            rng.random::<f64>(),
            rng.random::<f64>(),
            rng.random::<f64>(),
        ];
        let frame = random_frame(rng);
        out.push(Splat {
            pos: p,
            frame,
            sigma: [s, s * 0.6, s * 0.3],
            rgb,
            opacity: 0.3 + 0.6 * rng.random::<f64>(),
            reflect: None,
            truth: truth(classes::OTHER, FLOATER_INSTANCE),
        });
    }
    info.floaters = n_float;
    info
}

fn random_frame(rng: &mut ChaCha8Rng) -> DMat3 {
    let n = DVec3::new(
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
    )
    .try_normalize()
    .unwrap_or(DVec3::Z);
    frame_from_normal(n)
}

/// A tree: trunk (vertical elongated Gaussians) and an irregular crown of 3–5 blobs; returns
/// its solids (the trunk's box, one ball per blob).
fn tree(
    base: DVec3,
    n_crown: usize,
    inst: i32,
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) -> Vec<Shape> {
    let t = truth(classes::TREE, inst);
    let trunk_h = 2.0 + rng.random::<f64>() * 1.5;
    let trunk_r = 0.15 + rng.random::<f64>() * 0.1;
    for k in 0..40 {
        let a = k as f64 * 2.4;
        let z = base.z + trunk_h * (k as f64 + 0.5) / 40.0;
        let n = DVec3::new(a.cos(), a.sin(), 0.0);
        let p = DVec3::new(base.x, base.y, z) + n * trunk_r;
        out.push(Splat {
            pos: p,
            frame: frame_from_normal(n),
            sigma: [0.12, 0.3, 0.02],
            rgb: jitter(rng, [0.35, 0.25, 0.15], 0.04),
            opacity: 0.95,
            reflect: None,
            truth: t,
        });
    }
    let crown_r = 2.0 + rng.random::<f64>() * 1.2;
    let centre = DVec3::new(base.x, base.y, base.z + trunk_h + crown_r * 0.8);
    let blobs: Vec<(DVec3, f64)> = (0..3 + rng.random_range(0..3))
        .map(|_| {
            let off = DVec3::new(
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
                (rng.random::<f64>() - 0.5) * 0.6,
            ) * crown_r;
            (centre + off, crown_r * (0.55 + 0.3 * rng.random::<f64>()))
        })
        .collect();
    let mut shapes = vec![Shape::framed_box(
        base,
        DMat3::IDENTITY,
        DVec3::new(-trunk_r, -trunk_r, 0.0),
        DVec3::new(trunk_r, trunk_r, trunk_h),
    )];
    shapes.extend(blobs.iter().map(|(c, r)| Shape::Sphere {
        centre: c.to_array(),
        radius: *r,
    }));
    let green = [
        0.18 + 0.1 * rng.random::<f64>(),
        0.38 + 0.1 * rng.random::<f64>(),
        0.12,
    ];
    for _ in 0..n_crown {
        let (c, r) = blobs[rng.random_range(0..blobs.len())];
        // Mostly near the blob's surface: a leafy shell.
        let dir = DVec3::new(
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
        )
        .try_normalize()
        .unwrap_or(DVec3::Z);
        let rr = r * (0.6 + 0.4 * rng.random::<f64>().sqrt());
        let p = c + dir * rr;
        let shade = 0.75 + 0.35 * (dir.z * 0.5 + 0.5);
        out.push(Splat {
            pos: p,
            frame: random_frame(rng),
            sigma: [0.22, 0.16, 0.08],
            rgb: jitter(rng, green.map(|v| v * shade), 0.05),
            opacity: 0.85,
            reflect: None,
            truth: t,
        });
    }
    shapes
}

#[allow(clippy::too_many_arguments)]
fn box_surface(
    lo: DVec3,
    hi: DVec3,
    frame: DMat3,
    origin: DVec3,
    density: f64,
    rgb: [f64; 3],
    t: [i32; 5],
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) {
    let size = hi - lo;
    let faces = [
        (DVec3::X, size.y * size.z),
        (-DVec3::X, size.y * size.z),
        (DVec3::Y, size.x * size.z),
        (-DVec3::Y, size.x * size.z),
        (DVec3::Z, size.x * size.y),
    ];
    let sigma = 0.7 / density.sqrt();
    for (n, area) in faces {
        let count = (area * density).ceil() as usize;
        for _ in 0..count {
            let mut q = DVec3::new(
                lo.x + rng.random::<f64>() * size.x,
                lo.y + rng.random::<f64>() * size.y,
                lo.z + rng.random::<f64>() * size.z,
            );
            if n.x > 0.5 {
                q.x = hi.x;
            } else if n.x < -0.5 {
                q.x = lo.x;
            } else if n.y > 0.5 {
                q.y = hi.y;
            } else if n.y < -0.5 {
                q.y = lo.y;
            } else {
                q.z = hi.z;
            }
            let wn = frame * n;
            out.push(Splat {
                pos: origin + frame * q,
                frame: frame_from_normal(wn),
                sigma: [sigma, sigma, 0.01],
                rgb: jitter(rng, rgb, 0.02),
                opacity: 0.97,
                reflect: (n.z > 0.5).then_some((DVec3::Z, [0.15, 0.15, 0.15])),
                truth: t,
            });
        }
    }
}

/// A car: body box and a shorter cabin, long axis along the façade; returns the two boxes.
fn car(
    base: DVec3,
    facing: DVec3,
    inst: i32,
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) -> Vec<Shape> {
    let t = truth(classes::CAR, inst);
    let nh = DVec3::new(facing.x, facing.y, 0.0)
        .try_normalize()
        .unwrap_or(DVec3::Y);
    let along = DVec3::new(-nh.y, nh.x, 0.0);
    let frame = DMat3::from_cols(along, nh, DVec3::Z);
    let (l, w) = (
        4.2 + rng.random::<f64>() * 0.4,
        1.7 + rng.random::<f64>() * 0.2,
    );
    let paints = [
        [0.75, 0.1, 0.1],
        [0.1, 0.2, 0.6],
        [0.85, 0.85, 0.85],
        [0.1, 0.1, 0.1],
        [0.5, 0.5, 0.55],
    ];
    let paint = paints[rng.random_range(0..paints.len())];
    let body = (
        DVec3::new(-l / 2.0, -w / 2.0, 0.3),
        DVec3::new(l / 2.0, w / 2.0, 1.0),
    );
    let cabin = (
        DVec3::new(-l / 4.0, -w / 2.0 + 0.1, 1.0),
        DVec3::new(l / 5.0, w / 2.0 - 0.1, 1.45),
    );
    box_surface(body.0, body.1, frame, base, 80.0, paint, t, rng, out);
    box_surface(
        cabin.0,
        cabin.1,
        frame,
        base,
        80.0,
        [0.15, 0.18, 0.22],
        t,
        rng,
        out,
    );
    vec![
        Shape::framed_box(base, frame, body.0, body.1),
        Shape::framed_box(base, frame, cabin.0, cabin.1),
    ]
}

/// A person: a thin vertical cluster (legs/body) and a head; returns the body's box and the
/// head's ball.
fn person(base: DVec3, inst: i32, rng: &mut ChaCha8Rng, out: &mut Builder) -> Vec<Shape> {
    let t = truth(classes::PERSON, inst);
    let h = 1.6 + rng.random::<f64>() * 0.25;
    let shirt = [
        rng.random::<f64>(),
        rng.random::<f64>(),
        rng.random::<f64>(),
    ];
    let trousers = [0.15, 0.15, 0.25];
    for _ in 0..350 {
        let z = rng.random::<f64>() * (h - 0.25);
        let a = rng.random::<f64>() * std::f64::consts::TAU;
        let r = if z < 0.85 { 0.13 } else { 0.2 };
        let n = DVec3::new(a.cos(), a.sin(), 0.0);
        let p = base + DVec3::new(n.x * r, n.y * r * 0.7, z);
        out.push(Splat {
            pos: p,
            frame: frame_from_normal(n),
            sigma: [0.06, 0.1, 0.02],
            rgb: jitter(rng, if z < 0.85 { trousers } else { shirt }, 0.03),
            opacity: 0.95,
            reflect: None,
            truth: t,
        });
    }
    for _ in 0..60 {
        let d = DVec3::new(
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
        )
        .try_normalize()
        .unwrap_or(DVec3::Z);
        out.push(Splat {
            pos: base + DVec3::new(0.0, 0.0, h - 0.12) + d * 0.1,
            frame: frame_from_normal(d),
            sigma: [0.05, 0.05, 0.02],
            rgb: jitter(rng, [0.85, 0.68, 0.55], 0.03),
            opacity: 0.95,
            reflect: None,
            truth: t,
        });
    }
    vec![
        Shape::framed_box(
            base,
            DMat3::IDENTITY,
            DVec3::new(-0.2, -0.2 * 0.7, 0.0),
            DVec3::new(0.2, 0.2 * 0.7, h - 0.25),
        ),
        Shape::Sphere {
            centre: (base + DVec3::new(0.0, 0.0, h - 0.12)).to_array(),
            radius: 0.1,
        },
    ]
}
