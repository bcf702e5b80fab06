//! The CityGML side of a tile plan: one summary per top-level city object (its footprint centre
//! and box in the georeferenced ground plane, its box and sample points in the scene frame), and
//! the CityGML subset of a tile (a file whose every top-level object the tile keeps is linked; a
//! file holding objects of several tiles is cut at its `cityObjectMember` elements, so every kept
//! object keeps its gml:id, attributes and geometry byte for byte).
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use glam::DVec3;
use quick_xml::events::Event;

use super::TileError;
use crate::alignment::Alignment;

/// Points of one object kept for the visibility test of views.
const SAMPLES_PER_OBJECT: usize = 48;

/// One top-level city object (a building, or an object without parent) of the city model.
#[derive(Debug, Clone)]
pub struct Footprint {
    /// Its object id (gml:id, or the reader's stable derived id).
    pub id: String,
    /// The file it comes from (index into the scene's `citymodel/*.gml`).
    pub file: usize,
    /// Centre of its ground-plane box (georeferenced x, y).
    pub centre: [f64; 2],
    /// Ground-plane box `[x0, y0, x1, y1]` (georeferenced).
    pub ground: [f64; 4],
    /// Box in the scene frame (min, max).
    pub scene_min: DVec3,
    pub scene_max: DVec3,
    /// Polygon vertices in the scene frame (evenly subsampled).
    pub samples: Vec<DVec3>,
}

/// Reads every file and summarises its top-level objects that have geometry.
pub fn footprints(files: &[PathBuf], al: &Alignment) -> Result<Vec<Footprint>, TileError> {
    let mut out = Vec::new();
    for (fi, path) in files.iter().enumerate() {
        let model = crate::citygml::read(path)?;
        let root = |mut o: usize| {
            while let Some(p) = model.objects[o].parent {
                o = p;
            }
            o
        };
        let mut points: Vec<Vec<DVec3>> = vec![Vec::new(); model.objects.len()];
        for poly in model.used_polygons() {
            let Some(owner) = poly.owner else { continue };
            points[root(owner)].extend(poly.exterior.points.iter().copied());
        }
        for (o, obj) in model.objects.iter().enumerate() {
            let pts = &points[o];
            if obj.parent.is_some() || pts.is_empty() {
                continue;
            }
            let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            let (mut slo, mut shi) = (lo, hi);
            for &p in pts {
                lo = lo.min(p);
                hi = hi.max(p);
                let s = al.apply(p);
                slo = slo.min(s);
                shi = shi.max(s);
            }
            let step = pts.len().div_ceil(SAMPLES_PER_OBJECT).max(1);
            let samples = pts.iter().step_by(step).map(|&p| al.apply(p)).collect();
            out.push(Footprint {
                id: obj.object_id.clone(),
                file: fi,
                centre: [(lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0],
                ground: [lo.x, lo.y, hi.x, hi.y],
                scene_min: slo,
                scene_max: shi,
                samples,
            });
        }
    }
    let mut seen = BTreeSet::new();
    for f in &out {
        if !seen.insert(f.id.as_str()) {
            return Err(TileError::Invalid(format!(
                "{}: city object {} appears twice in the city model (in {} too); a tile plan needs unique ids",
                files[f.file].display(),
                f.id,
                files
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| out.iter().any(|g| g.id == f.id && g.file == *i))
                    .map(|(_, p)| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
    }
    Ok(out)
}

/// Writes the subset of `src` that keeps the top-level objects `keep` (by id) into `dst`: a link
/// when it keeps every object of the file, else the file without the `cityObjectMember`
/// elements of the others. Returns whether anything was written.
pub fn write_subset(
    src: &Path,
    all: &BTreeSet<&str>,
    keep: &BTreeSet<&str>,
    dst: &Path,
) -> Result<bool, TileError> {
    if keep.is_empty() {
        return Ok(false);
    }
    if keep.len() == all.len() {
        link(src, dst)?;
        return Ok(true);
    }
    let bytes = std::fs::read(src).map_err(|err| TileError::Io {
        path: src.to_path_buf(),
        err,
    })?;
    let text = std::str::from_utf8(&bytes).map_err(|_| {
        TileError::Invalid(format!(
            "{}: holds city objects of several tiles and is not UTF-8; split it into one file per building (or convert it to UTF-8)",
            src.display()
        ))
    })?;
    let drop = member_ranges(src, text)?
        .into_iter()
        .filter(|(_, id)| {
            id.as_deref()
                .is_some_and(|id| all.contains(id) && !keep.contains(id))
        })
        .map(|(r, _)| r)
        .collect::<Vec<_>>();
    let mut out = String::with_capacity(text.len());
    let mut at = 0;
    for r in drop {
        out.push_str(&text[at..r.start]);
        at = r.end;
    }
    out.push_str(&text[at..]);
    crate::fsutil::write_bytes(dst, out.as_bytes())?;
    Ok(true)
}

/// A `cityObjectMember`: its byte range and the gml:id of the object it holds.
type Member = (std::ops::Range<usize>, Option<String>);

/// The byte ranges of the `cityObjectMember` children of the root element, each with the gml:id
/// of the object it holds (its first child element's `gml:id`, `None` without one).
fn member_ranges(path: &Path, text: &str) -> Result<Vec<Member>, TileError> {
    let mut r = quick_xml::Reader::from_str(text);
    let mut depth = 0usize;
    let mut out = Vec::new();
    let mut open: Option<(usize, Option<String>, bool)> = None;
    loop {
        let before = r.buffer_position() as usize;
        let ev = r.read_event().map_err(|e| {
            TileError::Invalid(format!(
                "{}: XML error at byte {}: {e}",
                path.display(),
                r.error_position()
            ))
        })?;
        match ev {
            Event::Start(e) => {
                depth += 1;
                if depth == 2 && is_member(&e.local_name()) {
                    open = Some((before, None, false));
                } else if depth == 3 {
                    first_child(&mut open, &e);
                }
            }
            Event::Empty(e) if depth == 2 => first_child(&mut open, &e),
            Event::End(e) => {
                if depth == 2
                    && is_member(&e.local_name())
                    && let Some((start, id, _)) = open.take()
                {
                    out.push((start..r.buffer_position() as usize, id));
                }
                depth = depth.saturating_sub(1);
            }
            Event::Eof => break,
            _ => {}
        }
    }
    Ok(out)
}

/// Records the gml:id of the first child element of an open member.
fn first_child(
    open: &mut Option<(usize, Option<String>, bool)>,
    e: &quick_xml::events::BytesStart<'_>,
) {
    if let Some((_, id, seen)) = open.as_mut()
        && !*seen
    {
        *seen = true;
        *id = gml_id(e);
    }
}

fn is_member(local: &quick_xml::name::LocalName<'_>) -> bool {
    let l: &str = local.as_ref();
    l == "cityObjectMember"
}

fn gml_id(e: &quick_xml::events::BytesStart<'_>) -> Option<String> {
    e.attributes().flatten().find_map(|a| {
        let key = a.key.local_name();
        let k: &str = key.as_ref();
        (k == "id").then(|| a.value.to_string())
    })
}

/// A symbolic link `dst` → the absolute path of `src` (inputs are linked, never copied).
pub fn link(src: &Path, dst: &Path) -> Result<(), TileError> {
    let abs = src.canonicalize().map_err(|err| TileError::Io {
        path: src.to_path_buf(),
        err,
    })?;
    if let Some(parent) = dst.parent() {
        crate::fsutil::create_dir(parent)?;
    }
    let _ = std::fs::remove_file(dst);
    std::os::unix::fs::symlink(&abs, dst).map_err(|err| TileError::Io {
        path: dst.to_path_buf(),
        err,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn members_are_found_with_their_ids() {
        let text = "<?xml version=\"1.0\"?>\n<core:CityModel xmlns:core=\"c\" xmlns:gml=\"g\">\
            <gml:boundedBy/>\
            <core:cityObjectMember><bldg:Building gml:id=\"A\"><x/></bldg:Building></core:cityObjectMember>\
            <core:cityObjectMember><bldg:Building gml:id=\"B\"/></core:cityObjectMember>\
            <cityObjectMember><Building><y/></Building></cityObjectMember></core:CityModel>";
        let m = member_ranges(Path::new("t.gml"), text).unwrap();
        assert_eq!(m.len(), 3);
        assert_eq!(m[0].1.as_deref(), Some("A"));
        assert_eq!(m[1].1.as_deref(), Some("B"));
        assert_eq!(m[2].1, None);
        assert!(text[m[0].0.clone()].starts_with("<core:cityObjectMember>"));
        assert!(text[m[0].0.clone()].ends_with("</core:cityObjectMember>"));
        assert_eq!(
            &text[m[1].0.clone()],
            "<core:cityObjectMember><bldg:Building gml:id=\"B\"/></core:cityObjectMember>"
        );
    }
}
