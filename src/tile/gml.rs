//! The CityGML side of a tile plan: one summary per top-level city object (its footprint centre
//! and box in the georeferenced ground plane, its box and sample points in the scene frame), and
//! the CityGML subset of a tile (a file whose every top-level object the tile keeps is linked; a
//! file holding objects of several tiles is cut at its `cityObjectMember` elements, so every kept
//! object keeps its gml:id, attributes and geometry byte for byte). An object whose id another
//! object of the city model has (in another file, or earlier in its own) is renamed as
//! `gs4city run` renames it (`citygml::disambiguate`, `id~n`), and its subset carries that name
//! as its gml:id, so each tile's run, the merge and queries know it by the same id.
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
    /// Its object id: the gml:id (or the reader's stable derived id), renamed `id~n` where an
    /// earlier object of the city model has that id ([`crate::citygml::disambiguate`]).
    pub id: String,
    /// The file it comes from (index into the plan's city-model files).
    pub file: usize,
    /// Byte offset of its start tag in the file (its identity within the file).
    pub offset: u64,
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

/// What [`footprints`] found.
#[derive(Debug, Clone, Default)]
pub struct Footprints {
    pub feet: Vec<Footprint>,
    /// Per file: the objects whose id differs from the gml:id they are written with, or may
    /// (the start-tag offset, the id the plan knows them by).
    pub names: Vec<Vec<(u64, String)>>,
    /// One line per object renamed because another file uses its id, naming both files.
    pub warnings: Vec<String>,
}

/// Reads every file and summarises its top-level objects that have geometry; ids repeated
/// across files are told apart as `gs4city run` tells them apart. Memory: the geometry of one
/// file at a time, and the ids of all.
pub fn footprints(files: &[PathBuf], al: &Alignment) -> Result<Footprints, TileError> {
    let mut out = Vec::new();
    let mut roots = Vec::new();
    let mut models = Vec::with_capacity(files.len());
    for (fi, path) in files.iter().enumerate() {
        if crate::cityjson::is_cityjson_name(path) {
            return Err(TileError::Invalid(format!(
                "{}: CityJSON; `gs4city tile` cuts CityGML files only (`gs4city run` reads CityJSON untiled): convert the model to CityGML to tile it",
                path.display()
            )));
        }
        let mut model = crate::citygml::read(path)?;
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
                offset: obj.offset,
                centre: [(lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0],
                ground: [lo.x, lo.y, hi.x, hi.y],
                scene_min: slo,
                scene_max: shi,
                samples,
            });
            roots.push(o);
        }
        // Only the ids are kept for the disambiguation.
        model.polygons = Vec::new();
        model.textures = Vec::new();
        model.materials = Vec::new();
        for o in &mut model.objects {
            o.attributes = Default::default();
        }
        models.push(model);
    }
    let parsed: Vec<Vec<String>> = models
        .iter()
        .map(|m| m.objects.iter().map(|o| o.object_id.clone()).collect())
        .collect();
    let warnings = crate::citygml::disambiguate(&mut models)
        .iter()
        .map(ToString::to_string)
        .collect();
    for (f, &o) in out.iter_mut().zip(&roots) {
        f.id = models[f.file].objects[o].object_id.clone();
    }
    // Renamed here, or by the reader within the file (`id~n`: a literal `~` is checked too).
    let names = models
        .iter()
        .zip(&parsed)
        .map(|(m, parsed)| {
            m.objects
                .iter()
                .zip(parsed)
                .filter(|(o, p)| o.has_gml_id && (o.object_id != **p || p.contains('~')))
                .map(|(o, _)| (o.offset, o.object_id.clone()))
                .collect()
        })
        .collect();
    Ok(Footprints {
        feet: out,
        names,
        warnings,
    })
}

/// Writes the subset of `src` that keeps the top-level objects `keep` (by the offsets of their
/// start tags; `all`: those of every object of the file that a tile may own) into `dst`: a link
/// when it keeps every object of the file under the ids it is written with, else the file
/// without the `cityObjectMember` elements of the others, each kept object of `names` (offset,
/// id) carrying that id as its gml:id. Returns whether anything was written.
pub fn write_subset(
    src: &Path,
    all: &BTreeSet<u64>,
    keep: &BTreeSet<u64>,
    names: &[(u64, String)],
    dst: &Path,
) -> Result<bool, TileError> {
    if keep.is_empty() {
        return Ok(false);
    }
    if keep.len() == all.len() && names.is_empty() {
        link(src, dst)?;
        return Ok(true);
    }
    let bytes = std::fs::read(src).map_err(|err| TileError::Io {
        path: src.to_path_buf(),
        err,
    })?;
    // The reader's offsets count from after a byte-order mark.
    let text = std::str::from_utf8(crate::fsutil::strip_bom(&bytes)).map_err(|_| {
        TileError::Invalid(format!(
            "{}: holds city objects of several tiles, or objects renamed for ids used twice, and is not UTF-8; split it into one file per building (or convert it to UTF-8)",
            src.display()
        ))
    })?;
    let drop = member_ranges(src, text)?
        .into_iter()
        .map(|(r, _)| r)
        .filter(|r| {
            all.range(r.start as u64..r.end as u64)
                .any(|o| !keep.contains(o))
        })
        .collect::<Vec<_>>();
    let dropped = |o: usize| drop.iter().any(|r| r.contains(&o));
    let mut edits: Vec<(std::ops::Range<usize>, String)> =
        drop.iter().map(|r| (r.clone(), String::new())).collect();
    for (o, name) in names {
        let o = *o as usize;
        if dropped(o) {
            continue;
        }
        let (range, written) = id_value_at(text, o).ok_or_else(|| {
            TileError::Invalid(format!(
                "{}: no gml:id at byte {o}, where the reader found the object {name}; the file changed while the plan was made?",
                src.display()
            ))
        })?;
        if written != *name {
            edits.push((range, quick_xml::escape::escape(name.as_str()).into_owned()));
        }
    }
    if edits.is_empty() {
        link(src, dst)?;
        return Ok(true);
    }
    edits.sort_by_key(|(r, _)| r.start);
    let mut out = String::with_capacity(text.len());
    let mut at = 0;
    for (r, with) in edits {
        out.push_str(&text[at..r.start]);
        out.push_str(&with);
        at = r.end;
    }
    out.push_str(&text[at..]);
    crate::fsutil::write_bytes(dst, out.as_bytes())?;
    Ok(true)
}

/// The byte range of the `id` attribute's value (as written) of the start tag at byte `at`,
/// and the value as the reader reads it (normalised, unescaped).
fn id_value_at(text: &str, at: usize) -> Option<(std::ops::Range<usize>, String)> {
    let tail = text.get(at..)?;
    let mut r = quick_xml::Reader::from_str(tail);
    let (Ok(Event::Start(e)) | Ok(Event::Empty(e))) = r.read_event() else {
        return None;
    };
    let a = e.attributes().with_checks(false).flatten().find(|a| {
        let key = a.key.local_name();
        let k: &str = key.as_ref();
        k == "id"
    })?;
    let std::borrow::Cow::Borrowed(raw) = a.value else {
        return None;
    };
    // The value is a slice of `text`: its offset is the distance between the two starts.
    let start = (raw.as_ptr() as usize).checked_sub(text.as_ptr() as usize)?;
    let value = a
        .normalized_value(quick_xml::XmlVersion::Implicit1_0)
        .ok()?
        .into_owned();
    Some((start..start + raw.len(), value))
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

    #[test]
    fn the_id_of_a_start_tag_is_found_where_it_is_written() {
        let text = "<a><bldg:Building x=\"1\" gml:id=\"B&amp;1\"><y/></bldg:Building></a>";
        let at = text.find("<bldg").unwrap();
        let (r, v) = id_value_at(text, at).unwrap();
        assert_eq!(&text[r], "B&amp;1");
        assert_eq!(v, "B&1");
        assert_eq!(id_value_at(text, text.find("<y").unwrap()), None);
    }
}
