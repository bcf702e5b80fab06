//! Simulated building Gaussians on the TRUE city model: every used polygon of every file is
//! triangulated (local metric frame), sampled area-weighted, coloured from its
//! `ParameterizedTexture` image where it exists (else X3DMaterial, else a per-class palette
//! with procedural variation), windows made view-dependent (SH band 1), and windows/doors
//! recessed behind their wall plane. Also collects what the cameras and the objects need:
//! buildings (bbox, base), walls and openings with their outward normals.
use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;

use glam::DVec3;
use ndarray::Array3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::SynthError;
use super::config::Splats;
use super::gaussians::{Builder, Splat, frame_from_normal, hash01, value_noise};
use crate::citygml::{CityModel, Level};
use crate::citymodel::triangulate;
use crate::classes;
use crate::semantics::Entity;

/// One building (root feature) in the local metric frame.
#[derive(Debug, Clone)]
pub struct BuildingInfo {
    pub entity: i32,
    pub lo: DVec3,
    pub hi: DVec3,
}

/// A wall or opening with its area-weighted centroid and outward unit normal.
#[derive(Debug, Clone)]
pub struct Facet {
    pub entity: i32,
    pub class: i32,
    pub building: i32,
    /// The parent surface entity (openings), −1 if none.
    pub surface: i32,
    pub centroid: DVec3,
    pub normal: DVec3,
    pub area: f64,
    pub zmin: f64,
}

/// What the city part of the simulation produced besides Gaussians.
#[derive(Debug, Default)]
pub struct CityInfo {
    pub buildings: Vec<BuildingInfo>,
    pub walls: Vec<Facet>,
    pub openings: Vec<Facet>,
    /// Triangles in the local frame, for the footprint raster.
    pub triangles: Vec<[DVec3; 3]>,
    pub textured_gaussians: usize,
    pub textures_found: Vec<String>,
    pub textures_missing: Vec<String>,
    pub polygons_skipped: usize,
}

/// Base colour of a class (sRGB-ish 0..1).
pub fn palette(class: i32) -> [f64; 3] {
    match class {
        classes::WALL => [0.80, 0.74, 0.64],
        classes::ROOF => [0.55, 0.27, 0.20],
        classes::WINDOW => [0.20, 0.25, 0.32],
        classes::DOOR => [0.40, 0.26, 0.16],
        classes::GROUND_SURFACE => [0.45, 0.45, 0.45],
        classes::INSTALLATION => [0.60, 0.60, 0.58],
        classes::TREE => [0.22, 0.42, 0.16],
        classes::PERSON => [0.30, 0.30, 0.45],
        classes::CAR => [0.70, 0.10, 0.10],
        classes::ROAD => [0.30, 0.30, 0.31],
        classes::WATER => [0.15, 0.30, 0.45],
        _ => [0.9, 0.2, 0.8],
    }
}

struct PolyJob {
    file: usize,
    poly: usize,
    label: [i32; 3],
    instance: i32,
    class: i32,
    tri: triangulate::PolygonTriangles,
    /// uv per triangulation vertex (None where the polygon has no complete texture).
    uv: Option<(usize, Vec<[f64; 2]>)>,
    material: Option<[f64; 3]>,
}

/// Samples the buildings. `origin` is the georeferenced origin subtracted first (f64);
/// `texture_dirs[i]` is the folder the texture URIs of `models[i]` are relative to.
#[allow(clippy::too_many_arguments)]
pub fn build(
    texture_dirs: &[PathBuf],
    models: &[CityModel],
    entities: &[Entity],
    origin: DVec3,
    cfg: &Splats,
    rng: &mut ChaCha8Rng,
    out: &mut Builder,
) -> Result<CityInfo, SynthError> {
    let mut info = CityInfo::default();
    // Texture images: one list over all files; missing images are remembered as None.
    let mut images: Vec<Option<Array3<u8>>> = Vec::new();
    let mut image_index: HashMap<PathBuf, usize> = HashMap::new();
    let mut jobs: Vec<PolyJob> = Vec::new();
    let mut base = 0usize;
    let chain = crate::semantics::chains(entities);
    for (fi, m) in models.iter().enumerate() {
        let dir = texture_dirs[fi].clone();
        // ring id → (texture image index, uvs)
        let mut ring_uv: HashMap<&str, (usize, &Vec<[f64; 2]>)> = HashMap::new();
        if cfg.textures {
            for t in &m.textures {
                let path = dir.join(&t.image_uri);
                let idx = match image_index.get(&path) {
                    Some(&i) => i,
                    None => {
                        let img = if t.image_uri.is_empty() {
                            None
                        } else {
                            crate::imageio::read_rgb(&path).ok()
                        };
                        let name = path.display().to_string();
                        if img.is_some() {
                            info.textures_found.push(name);
                        } else {
                            info.textures_missing.push(name);
                        }
                        images.push(img);
                        image_index.insert(path.clone(), images.len() - 1);
                        images.len() - 1
                    }
                };
                for (ring, uvs) in &t.rings {
                    ring_uv.insert(ring.as_str(), (idx, uvs));
                }
            }
        }
        let mut mat_of: HashMap<&str, [f64; 3]> = HashMap::new();
        for mat in &m.materials {
            if let Some(d) = mat.diffuse {
                for t in &mat.targets {
                    mat_of.insert(t.trim_start_matches('#'), d);
                }
            }
        }
        for (pi, p) in m.polygons.iter().enumerate() {
            let (Some(owner), Some(lod)) = (p.owner, p.lod) else {
                continue;
            };
            if m.objects[owner].lod_used != Some(lod) {
                continue;
            }
            let c = chain[base + owner];
            let label = [c.feature, c.surface, c.part];
            let instance = if c.part >= 0 {
                c.part
            } else if c.surface >= 0 {
                c.surface
            } else {
                c.feature
            };
            let class = classes::of_entity(entities, instance);
            let ext: Vec<DVec3> = p.exterior.points.iter().map(|q| *q - origin).collect();
            let holes: Vec<Vec<DVec3>> = p
                .interiors
                .iter()
                .map(|r| r.points.iter().map(|q| *q - origin).collect())
                .collect();
            let tri = match triangulate::triangulate(&ext, &holes) {
                Ok(t) => t,
                Err(_) => {
                    info.polygons_skipped += 1;
                    continue;
                }
            };
            // Texture coordinates per triangulation vertex, matched by exact position.
            let mut known: Vec<(DVec3, [f64; 2], usize)> = Vec::new();
            for (ring, pts) in
                std::iter::once((&p.exterior, &ext)).chain(p.interiors.iter().zip(&holes))
            {
                if let Some((img, uvs)) = ring.id.as_deref().and_then(|id| ring_uv.get(id))
                    && uvs.len() == pts.len()
                {
                    for (q, uv) in pts.iter().zip(uvs.iter()) {
                        known.push((*q, *uv, *img));
                    }
                }
            }
            let uv = if known.is_empty() {
                None
            } else {
                let mut img0 = None;
                let mut v = Vec::with_capacity(tri.vertices.len());
                for q in &tri.vertices {
                    match known.iter().find(|k| k.0 == *q) {
                        Some(k) => {
                            img0 = Some(k.2);
                            v.push(k.1);
                        }
                        None => break,
                    }
                }
                match img0 {
                    Some(i) if v.len() == tri.vertices.len() && images[i].is_some() => Some((i, v)),
                    _ => None,
                }
            };
            let material =
                p.id.as_deref()
                    .and_then(|id| mat_of.get(id))
                    .or_else(|| mat_of.get(m.objects[owner].object_id.as_str()))
                    .copied();
            jobs.push(PolyJob {
                file: fi,
                poly: pi,
                label,
                instance,
                class,
                tri,
                uv,
                material,
            });
        }
        base += m.objects.len();
    }

    // Buildings: bbox per root feature.
    let mut bld: BTreeMap<i32, (DVec3, DVec3)> = BTreeMap::new();
    for j in &jobs {
        let b = entities[j.label[0].max(0) as usize].building;
        let e = bld
            .entry(b)
            .or_insert((DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)));
        for v in &j.tri.vertices {
            e.0 = e.0.min(*v);
            e.1 = e.1.max(*v);
        }
    }
    info.buildings = bld
        .iter()
        .map(|(&entity, &(lo, hi))| BuildingInfo { entity, lo, hi })
        .collect();

    // Area-weighted normals per surface / part entity, oriented outward (away from the
    // building's vertical axis; near-horizontal ones upward).
    let mut acc: BTreeMap<i32, (DVec3, DVec3, f64, f64, i32)> = BTreeMap::new();
    for j in &jobs {
        let n = if models[j.file].polygons[j.poly].reversed {
            -j.tri.normal
        } else {
            j.tri.normal
        };
        let c = j.tri.vertices.iter().copied().sum::<DVec3>() / j.tri.vertices.len() as f64;
        let zmin = j
            .tri
            .vertices
            .iter()
            .map(|v| v.z)
            .fold(f64::INFINITY, f64::min);
        for key in [j.label[1], j.label[2]] {
            if key < 0 {
                continue;
            }
            let e = acc
                .entry(key)
                .or_insert((DVec3::ZERO, DVec3::ZERO, 0.0, f64::INFINITY, 0));
            // Orient each polygon's normal outward before summing (files mix orientations).
            let b = entities[key as usize].building;
            let centre = bld.get(&b).map(|(lo, hi)| (*lo + *hi) * 0.5).unwrap_or(c);
            let out = outward(n, c, centre);
            e.0 += out * j.tri.area;
            e.1 += c * j.tri.area;
            e.2 += j.tri.area;
            e.3 = e.3.min(zmin);
            e.4 = b;
        }
    }
    let facet = |id: i32| -> Option<Facet> {
        let (n, c, a, zmin, b) = *acc.get(&id)?;
        if a <= 0.0 {
            return None;
        }
        Some(Facet {
            entity: id,
            class: classes::of_entity(entities, id),
            building: b,
            surface: entities[id as usize].parent.unwrap_or(-1),
            centroid: c / a,
            normal: n.try_normalize().unwrap_or(DVec3::X),
            area: a,
            zmin,
        })
    };
    for &id in acc.keys() {
        let class = classes::of_entity(entities, id);
        let level = entities[id as usize].level;
        match (level, class) {
            (Level::Part, classes::WINDOW | classes::DOOR) => {
                if let Some(f) = facet(id) {
                    info.openings.push(f);
                }
            }
            (Level::Surface, classes::WALL)
                if entities[id as usize].class == crate::semantics::Class::WallSurface =>
            {
                if let Some(f) = facet(id)
                    && f.normal.z.abs() < 0.3
                {
                    info.walls.push(f);
                }
            }
            _ => {}
        }
    }

    // Sample.
    let spacing = 1.0 / cfg.density.sqrt();
    let sigma = spacing * cfg.scale_factor;
    for j in &jobs {
        let poly_n = if models[j.file].polygons[j.poly].reversed {
            -j.tri.normal
        } else {
            j.tri.normal
        };
        let b = entities[j.label[0].max(0) as usize].building;
        let centre = bld
            .get(&b)
            .map(|(lo, hi)| (*lo + *hi) * 0.5)
            .unwrap_or(DVec3::ZERO);
        let pc = j.tri.vertices.iter().copied().sum::<DVec3>() / j.tri.vertices.len() as f64;
        let n_out = outward(poly_n, pc, centre);
        let frame = frame_from_normal(n_out);
        // Recess: openings move along their wall's inward normal.
        let shift = if matches!(j.class, classes::WINDOW | classes::DOOR) && j.label[2] >= 0 {
            let wall_n = if j.label[1] >= 0 {
                acc.get(&j.label[1])
                    .map(|a| a.0)
                    .and_then(|v| v.try_normalize())
            } else {
                None
            }
            .or_else(|| acc.get(&j.label[2]).and_then(|a| a.0.try_normalize()))
            .unwrap_or(n_out);
            -wall_n * cfg.recess
        } else {
            DVec3::ZERO
        };
        let base_rgb = j.material.unwrap_or_else(|| palette(j.class));
        let tint = 0.9 + 0.2 * hash01(j.instance as u64, 17);
        let glass = j.class == classes::WINDOW;
        let truth = [j.class, j.instance, j.label[0], j.label[1], j.label[2]];
        for t in &j.tri.triangles {
            let [a, b2, c] = t.map(|i| j.tri.vertices[i as usize]);
            let area = 0.5 * (b2 - a).cross(c - a).length();
            let expect = area * cfg.density;
            let mut count = expect.floor() as usize;
            if rng.random::<f64>() < expect - expect.floor() {
                count += 1;
            }
            for _ in 0..count {
                let (mut u, mut v) = (rng.random::<f64>(), rng.random::<f64>());
                if u + v > 1.0 {
                    u = 1.0 - u;
                    v = 1.0 - v;
                }
                let w = 1.0 - u - v;
                let p = a * w + b2 * u + c * v;
                let jit = [0, 1, 2].map(|_| (rng.random::<f64>() - 0.5) * 2.0 * cfg.color_jitter);
                let mut rgb = None;
                if let Some((img, uvs)) = &j.uv
                    && let Some(im) = &images[*img]
                {
                    let [ia, ib, ic] = t.map(|i| uvs[i as usize]);
                    let tu = ia[0] * w + ib[0] * u + ic[0] * v;
                    let tv = ia[1] * w + ib[1] * u + ic[1] * v;
                    rgb = Some(texel(im, tu, tv));
                }
                let rgb = match rgb {
                    Some(c) => {
                        info.textured_gaussians += 1;
                        [0, 1, 2].map(|k| c[k] + jit[k])
                    }
                    None => {
                        let nz = value_noise(p, 1.3, j.class as u64) * 0.08
                            + value_noise(p, 0.3, 99) * 0.04;
                        [0, 1, 2].map(|k| base_rgb[k] * tint * (1.0 + nz) + jit[k])
                    }
                };
                let reflect = glass.then(|| {
                    let g = cfg.glass_reflection;
                    (DVec3::Z * 0.8 + n_out * 0.5, [g * 0.8, g * 0.9, g])
                });
                out.push(Splat {
                    pos: p + shift,
                    frame,
                    sigma: [sigma, sigma, cfg.thickness],
                    rgb,
                    opacity: cfg.opacity,
                    reflect,
                    truth,
                });
            }
        }
        for tri in &j.tri.triangles {
            let v = tri.map(|i| j.tri.vertices[i as usize]);
            info.triangles.push(v);
        }
    }
    Ok(info)
}

/// `n` oriented away from the building's vertical axis through `centre` (near-horizontal
/// surfaces: upward).
fn outward(n: DVec3, at: DVec3, centre: DVec3) -> DVec3 {
    if n.z.abs() > 0.7 {
        return if n.z < 0.0 { -n } else { n };
    }
    let d = DVec3::new(at.x - centre.x, at.y - centre.y, 0.0);
    if n.dot(d) < 0.0 { -n } else { n }
}

/// The texel at texture coordinates `(u, v)` (wrapped; `v` up), RGB 0..1.
fn texel(im: &Array3<u8>, u: f64, v: f64) -> [f64; 3] {
    let (h, w, _) = im.dim();
    let fu = u - u.floor();
    let fv = v - v.floor();
    let x = ((fu * w as f64) as usize).min(w - 1);
    let y = (((1.0 - fv) * h as f64) as usize).min(h - 1);
    [0, 1, 2].map(|c| f64::from(im[[y, x, c]]) / 255.0)
}
