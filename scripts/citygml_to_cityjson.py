#!/usr/bin/env python3
"""An independent CityGML 1.0 / 2.0 / 3.0 -> CityJSON 2.0 (or CityJSONSeq) converter.

Written from the CityGML 2.0/3.0 and CityJSON 2.0 specifications with the standard library
(xml.etree) only, never from gs4city's Rust code: it is the reference of tests/cityjson.rs,
which checks that gs4city's CityJSON reader, given this file, finds the same objects,
hierarchy, attributes and polygons as gs4city's CityGML reader finds in the original.

Mapping (CityJSON 2.0 section "Semantics of geometric primitives"):
  * Building, BuildingPart, BuildingInstallation, BuildingConstructiveElement -> CityObjects
    (keyed by gml:id, or "<file stem>/<Class>[k]" without one), linked by parents/children;
  * thematic surfaces (WallSurface, RoofSurface, ...) and openings (Window/Door; CityGML 3.0
    WindowSurface/DoorSurface) -> semantic surfaces of their CityObject's geometry, an opening's
    "parent" being its wall; the gml:id, where there is one, is kept as the member "id";
  * per CityObject and LoD (1-3) one MultiSurface holding every polygon of that LoD found below
    it (exterior ring first, interior rings after; the closing point dropped), semantic value =
    the innermost thematic surface or opening around the polygon;
  * an xlink:href to a polygon that some CityObject already holds is not repeated; one to a
    polygon outside every CityObject is taken by the referencing object;
  * attributes: the simple CityGML attributes (measuredHeight, storeys, years, function, ...),
    gml:name/description and generic attributes (2.0 gen:*Attribute, 3.0 genericAttribute, set
    names joined with "/"), a unit of measure as {"value": v, "uom": u};
  * vertices quantised with scale 0.001 and the minimum as translate; the CRS from srsName
    (EPSG code) into metadata.referenceSystem.

Usage: citygml_to_cityjson.py IN.gml OUT.city.json [--seq]  (--seq writes CityJSONSeq: a header
line, then one CityJSONFeature per top-level CityObject with its own vertex list).
"""
import json
import re
import sys
import xml.etree.ElementTree as ET

XLINK = "{http://www.w3.org/1999/xlink}href"
CITY_OBJECTS = {"Building", "BuildingPart", "BuildingInstallation", "BuildingConstructiveElement"}
SEMANTIC = {
    "WallSurface": "WallSurface",
    "RoofSurface": "RoofSurface",
    "GroundSurface": "GroundSurface",
    "ClosureSurface": "ClosureSurface",
    "OuterCeilingSurface": "OuterCeilingSurface",
    "OuterFloorSurface": "OuterFloorSurface",
    "Window": "Window",
    "Door": "Door",
    "WindowSurface": "Window",
    "DoorSurface": "Door",
}
# CityGML simple attributes (core, building) and their types (schema types: LengthType,
# nonNegativeInteger, gYear are numbers; codes and dates are text).
NUMERIC = {"measuredHeight", "storeysAboveGround", "storeysBelowGround", "yearOfConstruction",
           "yearOfDemolition"}
TEXT = {"function", "usage", "class", "roofType", "storeyHeightsAboveGround",
        "storeyHeightsBelowGround", "creationDate", "terminationDate", "relativeToTerrain",
        "relativeToWater", "name", "description"}
SCALE = 0.001


def local(tag):
    return tag.rsplit("}", 1)[-1] if isinstance(tag, str) else ""


def namespace(tag):
    return tag[1:].split("}")[0] if isinstance(tag, str) and tag.startswith("{") else ""


def is_city(tag):
    return "opengis.net/citygml" in namespace(tag)


def is_gml(tag):
    return namespace(tag).startswith("http://www.opengis.net/gml")


def gml_id(el):
    for k, v in el.attrib.items():
        if local(k) == "id" and is_gml(k):
            return v
    return None


def number(text):
    try:
        return int(text)
    except ValueError:
        return float(text)


def ring_points(ring):
    """The points of a gml:LinearRing (posList or pos), closing point dropped."""
    pts = []
    for el in ring.iter():
        if local(el.tag) == "posList":
            dim = int(el.get("srsDimension", "3"))
            vals = [float(x) for x in el.text.split()]
            pts.extend(tuple(vals[i:i + dim]) for i in range(0, len(vals), dim))
        elif local(el.tag) == "pos":
            pts.append(tuple(float(x) for x in el.text.split()))
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts.pop()
    return pts


def polygon_rings(poly):
    ext, ints = None, []
    for ch in poly.iter():
        if local(ch.tag) == "exterior":
            ext = next((r for r in ch.iter() if local(r.tag) == "LinearRing"), None)
        elif local(ch.tag) == "interior":
            r = next((r for r in ch.iter() if local(r.tag) == "LinearRing"), None)
            if r is not None:
                ints.append(r)
    if ext is None:
        return None
    return [ring_points(ext)] + [ring_points(r) for r in ints]


class Converter:
    def __init__(self, path):
        self.path = path
        self.stem = re.sub(r"\.[^.]*$", "", path.rsplit("/", 1)[-1])
        self.objects = []      # CityObject records, document order
        self.sems = []         # semantic records, document order
        self.polys = []        # polygon records
        self.poly_by_el = {}   # id(element) -> polygon record
        self.refs = []         # (href target, co, sem, lod)
        self.ids = {}          # gml:id -> element
        self.siblings = {}
        self.srs = None

    def attrs(self, el):
        """Simple and generic attributes among the direct children of a city object."""
        out = {}

        def put(k, v):
            if k in out:
                out[k] = (out[k] if isinstance(out[k], list) else [out[k]]) + [v]
            else:
                out[k] = v

        def generic(g, prefix):
            name = local(g.tag)
            if name in ("genericAttributeSet", "GenericAttributeSet"):
                set_name = g.get("name")
                for c in g:
                    if local(c.tag) == "name" and set_name is None:
                        set_name = (c.text or "").strip()
                for c in g:
                    if local(c.tag) == "value" and name == "GenericAttributeSet":
                        for a in c:
                            generic(a, prefix + set_name + "/")
                    elif local(c.tag).endswith("Attribute"):
                        generic(c, prefix + set_name + "/")
                return
            key, value, uom = g.get("name"), None, None
            for c in g:
                if local(c.tag) == "name":
                    key = (c.text or "").strip()
                elif local(c.tag) == "value":
                    value = (c.text or "").strip()
                    uom = c.get("uom", uom)
            uom = g.get("uom", uom)
            if key is None or value is None:
                return
            kind = name.lower()
            if kind.startswith("int"):
                try:
                    value = int(value)
                except ValueError:
                    pass
            elif kind.startswith("double") or kind.startswith("measure"):
                try:
                    value = float(value)
                except ValueError:
                    pass
            put(prefix + key, {"value": value, "uom": uom} if uom else value)

        for ch in el:
            name = local(ch.tag)
            if (is_city(ch.tag) or is_gml(ch.tag)) and (name in NUMERIC or name in TEXT):
                text = (ch.text or "").strip()
                if not text:
                    continue
                v = text
                if name in NUMERIC:
                    try:
                        v = number(text)
                    except ValueError:
                        v = text
                uom = ch.get("uom")
                put(name, {"value": v, "uom": uom} if uom else v)
            elif name.endswith("Attribute") and "generics" in namespace(ch.tag):
                generic(ch, "")
            elif name == "genericAttribute":
                for g in ch:
                    generic(g, "")
            elif name == "height":
                for h in ch:
                    if local(h.tag) != "Height":
                        continue
                    for c in h:
                        t, text = local(c.tag), (c.text or "").strip()
                        if t == "value":
                            uom = c.get("uom")
                            v = float(text)
                            put("height", {"value": v, "uom": uom} if uom else v)
                        elif t in ("highReference", "lowReference", "status"):
                            put("height." + t, text)
        return out

    def walk(self, el, co, sem, lod):
        tag = local(el.tag)
        if isinstance(el.tag, str):
            gid = gml_id(el)
            if gid is not None:
                self.ids.setdefault(gid, el)
            if self.srs is None and el.get("srsName"):
                self.srs = el.get("srsName")
        if is_city(el.tag) and tag in CITY_OBJECTS:
            rec = {"class": tag, "gml_id": gml_id(el), "parent": co, "attributes": self.attrs(el),
                   "children": []}
            if co is not None:
                co["children"].append(rec)
            self.objects.append(rec)
            for ch in el:
                self.walk(ch, rec, None, None)
            return
        if is_city(el.tag) and tag in SEMANTIC and co is not None:
            rec = {"type": SEMANTIC[tag], "gml_id": gml_id(el), "co": co, "parent": sem,
                   "attributes": self.attrs(el)}
            self.sems.append(rec)
            for ch in el:
                self.walk(ch, co, rec, None)
            return
        m = re.fullmatch(r"lod(\d)[A-Za-z]+", tag)
        if m:
            lod = int(m.group(1))
        if is_gml(el.tag) and tag in ("Polygon", "Triangle", "Rectangle", "PolygonPatch"):
            rings = polygon_rings(el)
            if rings is not None:
                rec = {"co": co, "sem": sem, "lod": lod, "rings": rings}
                self.polys.append(rec)
                self.poly_by_el[id(el)] = rec
            return
        href = el.get(XLINK)
        if href is not None and href.startswith("#") and lod is not None:
            self.refs.append((href[1:], co, sem, lod))
        for ch in el:
            self.walk(ch, co, sem, lod)

    def resolve(self):
        for target, co, sem, lod in self.refs:
            el = self.ids.get(target)
            if el is None or co is None:
                continue
            for p in el.iter():
                rec = self.poly_by_el.get(id(p))
                if rec is not None and (rec["co"] is None or rec["lod"] is None):
                    rec["co"], rec["sem"], rec["lod"] = co, sem, lod

    def object_ids(self):
        used = {o["gml_id"] for o in self.objects if o["gml_id"]}
        counts = {}
        for o in self.objects:
            k = (id(o["parent"]) if o["parent"] else None, o["class"])
            counts[k] = counts.get(k, 0) + 1
            if o["gml_id"]:
                o["id"] = o["gml_id"]
                continue
            base = o["parent"]["id"] if o["parent"] else self.stem
            o["id"] = f"{base}/{o['class']}[{counts[k]}]"
            assert o["id"] not in used
            used.add(o["id"])

    def city_objects(self, roots):
        """CityObjects (dict) and their vertices for the given root objects and descendants."""
        verts, index, out = [], {}, {}

        def vid(p):
            q = tuple(round((p[i] - self.translate[i]) / SCALE) for i in range(3))
            if q not in index:
                index[q] = len(verts)
                verts.append(list(q))
            return index[q]

        def emit(o):
            j = {"type": o["class"]}
            if o["attributes"]:
                j["attributes"] = o["attributes"]
            if o["parent"] is not None:
                j["parents"] = [o["parent"]["id"]]
            if o["children"]:
                j["children"] = [c["id"] for c in o["children"]]
            mine = [p for p in self.polys if p["co"] is o and p["lod"] in (1, 2, 3)]
            sems = [s for s in self.sems if s["co"] is o]
            lods = sorted({p["lod"] for p in mine})
            if not lods and sems:
                lods = [3]
            geoms = []
            for lod in lods:
                polys = [p for p in mine if p["lod"] == lod]
                # Semantic surfaces: those with polygons of this LoD and their ancestors; the
                # highest LoD also carries the ones without any polygon.
                keep = set()
                for p in polys:
                    s = p["sem"]
                    while s is not None:
                        keep.add(id(s))
                        s = s["parent"]
                if lod == lods[-1]:
                    with_polys = {id(p["sem"]) for p in mine if p["sem"] is not None}
                    for s in sems:
                        if id(s) not in with_polys:
                            t = s
                            while t is not None:
                                keep.add(id(t))
                                t = t["parent"]
                chosen = [s for s in sems if id(s) in keep]
                pos = {id(s): i for i, s in enumerate(chosen)}
                surfaces = []
                for s in chosen:
                    js = {"type": s["type"]}
                    if s["gml_id"]:
                        js["id"] = s["gml_id"]
                    if s["parent"] is not None:
                        js["parent"] = pos[id(s["parent"])]
                    kids = [pos[id(c)] for c in chosen if c["parent"] is s]
                    if kids:
                        js["children"] = kids
                    js.update(s["attributes"])
                    surfaces.append(js)
                boundaries = [[[vid(q) for q in ring] for ring in p["rings"]] for p in polys]
                values = [pos[id(p["sem"])] if p["sem"] is not None else None for p in polys]
                g = {"type": "MultiSurface", "lod": str(lod), "boundaries": boundaries}
                if surfaces:
                    g["semantics"] = {"surfaces": surfaces, "values": values}
                geoms.append(g)
            j["geometry"] = geoms
            out[o["id"]] = j
            for c in o["children"]:
                emit(c)

        for r in roots:
            emit(r)
        return out, verts

    def convert(self, seq):
        root = ET.parse(self.path).getroot()
        self.walk(root, None, None, None)
        self.resolve()
        self.object_ids()
        pts = [q for p in self.polys for r in p["rings"] for q in r]
        self.translate = [min(q[i] for q in pts) for i in range(3)] if pts else [0.0, 0.0, 0.0]
        header = {"type": "CityJSON", "version": "2.0",
                  "transform": {"scale": [SCALE] * 3, "translate": self.translate},
                  "metadata": {}}
        m = re.search(r"EPSG[^0-9]*(\d+)", self.srs or "")
        if m:
            header["metadata"]["referenceSystem"] = \
                f"https://www.opengis.net/def/crs/EPSG/0/{m.group(1)}"
        roots = [o for o in self.objects if o["parent"] is None]
        if not seq:
            cos, verts = self.city_objects(roots)
            return [dict(header, CityObjects=cos, vertices=verts)]
        lines = [dict(header, CityObjects={}, vertices=[])]
        for r in roots:
            cos, verts = self.city_objects([r])
            lines.append({"type": "CityJSONFeature", "id": r["id"], "CityObjects": cos,
                          "vertices": verts})
        return lines


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    seq = "--seq" in sys.argv
    if len(args) != 2:
        sys.exit(__doc__)
    docs = Converter(args[0]).convert(seq)
    with open(args[1], "w", encoding="utf-8") as f:
        if seq:
            for d in docs:
                f.write(json.dumps(d, ensure_ascii=False, separators=(",", ":")) + "\n")
        else:
            json.dump(docs[0], f, ensure_ascii=False)


if __name__ == "__main__":
    main()
