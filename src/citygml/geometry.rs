//! The geometry builder: gml: elements under an `lodN…` property become polygons
//! (patches, exterior and interior rings, `pos` / `posList` / `coordinates` in 2D or 3D,
//! `OrientableSurface` orientation); gml:ids of polygons and of the containers around them
//! are indexed so `xlink:href` references can be resolved after EOF (shared geometry is
//! counted once). Curves, points and implicit geometry are skipped and counted.
use glam::DVec3;

use super::CityGmlError;
use super::model::*;
use super::reader::{Attrs, Parser, Tag};

#[derive(Debug, Clone, Copy)]
pub(super) enum CoordKind {
    Pos,
    PosList,
    Coordinates,
}

pub(super) struct PolyBuilder {
    id: Option<String>,
    exterior: Option<Ring>,
    interiors: Vec<Ring>,
    line: u64,
    owner: Option<usize>,
    lod: Option<u8>,
    reversed: bool,
    bad: Option<String>,
}

pub(super) struct Reference {
    href: String,
    owner: Option<usize>,
    lod: Option<u8>,
    reversed: bool,
    line: u64,
}

/// Steps (gml:ids visited) a file's nested xlink references may take in all (`resolve_references`).
const XLINK_BUDGET: usize = 1_000_000;

const GEOM_CONTAINERS: &[&str] = &[
    "MultiSurface",
    "CompositeSurface",
    "Solid",
    "CompositeSolid",
    "MultiSolid",
    "Shell",
    "Surface",
    "OrientableSurface",
    "TriangulatedSurface",
    "Tin",
    "PolyhedralSurface",
    "MultiGeometry",
    "GeometricComplex",
    "surfaceMember",
    "surfaceMembers",
    "solidMember",
    "geometryMember",
    "geometryMembers",
    "baseSurface",
    "patches",
    "trianglePatches",
    "polygonPatches",
    "exterior",
    "interior",
    "member",
];
const CURVES: &[&str] = &[
    "LineString",
    "Curve",
    "MultiCurve",
    "CompositeCurve",
    "OrientableCurve",
    "Point",
    "MultiPoint",
    "LineStringSegment",
    "Arc",
];
const PATCHES: &[&str] = &["Polygon", "Triangle", "PolygonPatch", "Rectangle"];

pub(super) fn lod_property(local: &str) -> Option<u8> {
    let rest = local.strip_prefix("lod")?;
    let d = rest.chars().next()?.to_digit(10)?;
    let kind = &rest[1..];
    if kind.is_empty() {
        return None;
    }
    Some(d as u8)
}

impl Parser {
    /// An `lodN…` geometry property: sets the current LoD (its end tag restores the previous
    /// one) and records its `xlink:href`; implicit geometry is skipped with a warning.
    pub(super) fn geometry_property(&mut self, local: &str, lod: u8, a: &Attrs, line: u64) -> Tag {
        if local.contains("Implicit") {
            self.stats.implicit_skipped += 1;
            self.warn(
                line,
                self.current_object()
                    .map(|o| self.objects[o].object_id.clone()),
                format!("{local}: implicit geometry is not supported, skipped"),
            );
            return Tag::Implicit;
        }
        let prev = self.lod;
        self.lod = Some(lod);
        if let Some(href) = &a.href {
            self.add_reference(href, line);
        }
        Tag::GeomProp(prev)
    }

    pub(super) fn gml_start(
        &mut self,
        local: &str,
        a: &Attrs,
        parent_is_object: bool,
        line: u64,
    ) -> Tag {
        if self.curve_depth > 0 {
            // Everything inside a skipped curve/point geometry is part of it.
            self.curve_depth += 1;
            return Tag::Curve;
        }
        if let Some(href) = &a.href
            && self.lod.is_some()
        {
            self.add_reference(href, line);
            return Tag::Plain;
        }
        if PATCHES.contains(&local) {
            if self.poly.is_some() {
                self.warn(
                    line,
                    a.gml_id.clone(),
                    format!("nested gml:{local} inside a polygon ignored"),
                );
                return Tag::Unknown;
            }
            self.stats.polygons += 1;
            self.poly = Some(PolyBuilder {
                id: a.gml_id.clone(),
                exterior: None,
                interiors: Vec::new(),
                line,
                owner: if self.lod.is_some() {
                    self.current_object()
                } else {
                    None
                },
                lod: self.lod,
                reversed: self.reversed_depth % 2 == 1,
                bad: None,
            });
            return Tag::Polygon;
        }
        if self.poly.is_some() {
            match local {
                "exterior" | "outerBoundaryIs" => {
                    self.ring_is_interior = Some(false);
                    return Tag::RingRole;
                }
                "interior" | "innerBoundaryIs" => {
                    self.ring_is_interior = Some(true);
                    self.stats.holes += 1;
                    return Tag::RingRole;
                }
                "LinearRing" => {
                    self.ring = Some(Ring {
                        id: a.gml_id.clone(),
                        points: Vec::new(),
                    });
                    return Tag::Ring;
                }
                "pos" | "posList" | "coordinates" if self.ring.is_some() => {
                    self.coord_dim = a
                        .srs_dimension
                        .as_deref()
                        .and_then(|d| d.trim().parse().ok())
                        .or_else(|| self.dim_stack.last().map(|&(_, d)| d))
                        .unwrap_or(3);
                    self.coord_cs = a.cs.clone().unwrap_or_else(|| ",".into());
                    self.coord_ts = a.ts.clone().unwrap_or_else(|| " ".into());
                    self.begin_text();
                    return Tag::Coords(match local {
                        "pos" => CoordKind::Pos,
                        "posList" => CoordKind::PosList,
                        _ => CoordKind::Coordinates,
                    });
                }
                "Ring" | "curveMember" => {
                    if let Some(pb) = self.poly.as_mut()
                        && pb.bad.is_none()
                    {
                        pb.bad = Some("gml:Ring made of curve members is not supported".into());
                    }
                    return Tag::Plain;
                }
                _ => {}
            }
        }
        if CURVES.contains(&local) || (local == "curveMember" && self.poly.is_none()) {
            if self.poly.is_none() && local != "curveMember" {
                self.stats.curves_skipped += 1;
            }
            self.curve_depth += 1;
            return Tag::Curve;
        }
        if GEOM_CONTAINERS.contains(&local) {
            let reversed = local == "OrientableSurface" && a.orientation.as_deref() == Some("-");
            if reversed {
                self.reversed_depth += 1;
            }
            let has_id = if let Some(id) = &a.gml_id {
                self.container_ids.push(id.clone());
                true
            } else {
                false
            };
            return Tag::Container(has_id, reversed);
        }
        if parent_is_object && matches!(local, "name" | "description") {
            self.begin_text();
            return Tag::Attr(local.to_string());
        }
        match local {
            "boundedBy" | "Envelope" | "lowerCorner" | "upperCorner" | "featureMember" => {
                Tag::Plain
            }
            _ => Tag::Unknown,
        }
    }

    fn add_reference(&mut self, href: &str, line: u64) {
        let href = href.trim_start_matches('#').to_string();
        for cid in &self.container_ids {
            self.container_refs
                .entry(cid.clone())
                .or_default()
                .push(href.clone());
        }
        self.references.push(Reference {
            href,
            owner: self.current_object(),
            lod: self.lod,
            reversed: self.reversed_depth % 2 == 1,
            line,
        });
    }

    /// The end of a `gml:LinearRing`: it becomes the polygon's exterior, or an interior.
    pub(super) fn finish_ring(&mut self) {
        let ring = self.ring.take().unwrap_or_default();
        if let Some(pb) = self.poly.as_mut() {
            match self.ring_is_interior {
                Some(true) => pb.interiors.push(ring),
                _ if pb.exterior.is_none() => pb.exterior = Some(ring),
                _ => {
                    if pb.bad.is_none() {
                        pb.bad = Some("second exterior ring".into());
                    }
                }
            }
        }
    }

    pub(super) fn finish_coords(&mut self, kind: CoordKind, line: u64) -> Result<(), CityGmlError> {
        let text = self.take_text();
        let dim = self.coord_dim;
        if !(2..=3).contains(&dim) {
            return Err(CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!("srsDimension {dim} is not supported (2 or 3)"),
            });
        }
        let mut values = Vec::new();
        let parse = |tok: &str| -> Result<f64, CityGmlError> {
            tok.parse::<f64>().map_err(|_| CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!("'{tok}' is not a number"),
            })
        };
        match kind {
            CoordKind::Pos | CoordKind::PosList => {
                for tok in text.split_ascii_whitespace() {
                    values.push(parse(tok)?);
                }
            }
            CoordKind::Coordinates => {
                let ts = self.coord_ts.clone();
                let cs = self.coord_cs.clone();
                let tuples: Vec<&str> = if ts.trim().is_empty() {
                    text.split_ascii_whitespace().collect()
                } else {
                    text.split(ts.as_str())
                        .filter(|s| !s.trim().is_empty())
                        .collect()
                };
                for tuple in tuples {
                    let parts: Vec<&str> = tuple.split(cs.as_str()).map(str::trim).collect();
                    if parts.len() != dim {
                        return Err(CityGmlError::Geometry {
                            path: self.path.clone(),
                            line,
                            id: self.poly.as_ref().and_then(|p| p.id.clone()),
                            message: format!(
                                "coordinate tuple '{tuple}' does not have {dim} values"
                            ),
                        });
                    }
                    for t in parts {
                        values.push(parse(t)?);
                    }
                }
            }
        }
        if values.len() % dim != 0 {
            return Err(CityGmlError::Geometry {
                path: self.path.clone(),
                line,
                id: self.poly.as_ref().and_then(|p| p.id.clone()),
                message: format!(
                    "{} coordinate values are not a multiple of srsDimension {dim}",
                    values.len()
                ),
            });
        }
        if let Some(ring) = self.ring.as_mut() {
            for c in values.chunks_exact(dim) {
                let z = if dim == 3 { c[2] } else { 0.0 };
                ring.points.push(DVec3::new(c[0], c[1], z));
            }
        }
        Ok(())
    }

    pub(super) fn finish_polygon(&mut self) {
        let Some(mut pb) = self.poly.take() else {
            return;
        };
        let ordinal = self.polygons.len();
        let exterior = pb.exterior.take().unwrap_or_default();
        if pb.bad.is_none() && exterior.points.is_empty() {
            pb.bad = Some("no exterior ring".into());
        }
        let mut poly = Polygon {
            id: pb.id.clone(),
            exterior,
            interiors: pb.interiors,
            owner: pb.owner,
            lod: pb.lod,
            reversed: pb.reversed,
            line: pb.line,
            ordinal,
        };
        for ring in std::iter::once(&mut poly.exterior).chain(poly.interiors.iter_mut()) {
            if ring.points.len() > 1 && ring.points.first() == ring.points.last() {
                ring.points.pop();
            }
        }
        if let Some(why) = pb.bad {
            // The warning names the file, line and gml:id already.
            let what = if poly.id.is_some() {
                "polygon".to_string()
            } else {
                poly.name()
            };
            self.warn(pb.line, pb.id.clone(), format!("{what} skipped: {why}"));
            poly.owner = None;
        }
        if let Some(id) = &poly.id {
            self.geometry_ids
                .entry(id.clone())
                .or_default()
                .push(ordinal);
        }
        for cid in &self.container_ids {
            self.geometry_ids
                .entry(cid.clone())
                .or_default()
                .push(ordinal);
        }
        self.polygons.push(poly);
    }

    /// xlink references: geometry owned inline is the same geometry, counted once. A reference
    /// to a container whose members are themselves references (a `CompositeSurface` of
    /// xlinks) is followed through them, cycles cut; all such following shares one budget of
    /// [`XLINK_BUDGET`] steps per file, beyond which a reference is skipped with a warning.
    pub(super) fn resolve_references(&mut self) {
        let mut budget = XLINK_BUDGET;
        for r in std::mem::take(&mut self.references) {
            let found = match self.geometry_ids.get(&r.href) {
                _ if self.container_refs.contains_key(&r.href) => {
                    self.nested_targets(&r.href, &mut budget)
                }
                Some(t) => Ok(t.clone()),
                None => Err(format!(
                    "dangling xlink:href=\"#{}\": no geometry with that gml:id, reference skipped",
                    r.href
                )),
            };
            match found {
                Err(why) => {
                    self.stats.xlinks_dangling += 1;
                    let id = r.owner.map(|o| self.objects[o].object_id.clone());
                    self.warn(r.line, id, why);
                }
                Ok(targets) => {
                    for t in targets {
                        let poly = &mut self.polygons[t];
                        if poly.owner.is_some() || r.owner.is_none() {
                            self.stats.xlinks_shared += 1;
                        } else {
                            poly.owner = r.owner;
                            poly.lod = r.lod;
                            poly.reversed ^= r.reversed;
                            self.stats.xlinks_adopted += 1;
                        }
                    }
                }
            }
        }
    }

    /// The polygons of container `href` through its xlink members, breadth first, each
    /// gml:id visited once (cycles cut); `Err` with the reason when none is found or the
    /// budget runs out.
    fn nested_targets(&self, href: &str, budget: &mut usize) -> Result<Vec<usize>, String> {
        let mut seen: std::collections::HashSet<&str> = std::collections::HashSet::new();
        let mut queue = std::collections::VecDeque::from([href]);
        let mut out = Vec::new();
        seen.insert(href);
        while let Some(h) = queue.pop_front() {
            if *budget == 0 {
                return Err(format!(
                    "xlink:href=\"#{href}\" names a container of xlinks nested beyond the reader's budget ({XLINK_BUDGET} steps per file), reference skipped"
                ));
            }
            *budget -= 1;
            if let Some(t) = self.geometry_ids.get(h) {
                out.extend_from_slice(t);
            }
            for next in self.container_refs.get(h).into_iter().flatten() {
                if seen.insert(next.as_str()) {
                    queue.push_back(next.as_str());
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        if out.is_empty() {
            return Err(format!(
                "xlink:href=\"#{href}\" names a container whose xlink members name no geometry, reference skipped"
            ));
        }
        Ok(out)
    }
}
