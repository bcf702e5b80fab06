#!/usr/bin/env python3
"""What cjio (pip, the CityJSON reference tool of TU Delft) reads from a CityJSON file or a
CityJSONSeq stream: the reference of tests/cityjson.rs for gs4city's CityJSON reader.

cjio loads the file (a CityJSONSeq line by line with its own add_cityjsonfeature, which
re-indexes every feature's vertices), checks the version, and decodes the quantised vertices
(decompress: scale and translate). From that this script reports, as JSON on stdout:
  objects:  {id: {"type", "parents", "attributes"}} of the building CityObjects;
  semantic: {type: count} of the semantic surfaces of the geometries used;
  polygons: number of surfaces of the geometries used;
  coord_sum: [sx, sy, sz], the sum of the decoded ring vertices of those surfaces.
"Used" follows the CityGML rule gs4city documents: per building (root object), LoD 3 if
the building or a descendant has it, else 2, else 1; per object the highest LoD string of
that level, the first geometry of it.

Usage: cjio_summary.py FILE.city.json | FILE.city.jsonl
"""
import json
import sys

from cjio import cityjson

BUILDING = {"Building", "BuildingPart", "BuildingInstallation", "BuildingConstructiveElement"}
SURFACES = {"MultiSurface": 0, "CompositeSurface": 0, "Solid": 1, "MultiSolid": 2,
            "CompositeSolid": 2}


def load(path):
    if path.endswith(".jsonl"):
        with open(path, encoding="utf-8") as f:
            lines = [json.loads(line) for line in f if line.strip()]
        cm = cityjson.CityJSON(j=lines[0])
        cm.j.setdefault("CityObjects", {})
        cm.j.setdefault("vertices", [])
        for feature in lines[1:]:
            cm.add_cityjsonfeature(feature)
    else:
        with open(path, encoding="utf-8") as f:
            cm = cityjson.CityJSON(file=f)
    if cm.get_version() not in cityjson.CITYJSON_VERSIONS_SUPPORTED:
        sys.exit(f"cjio does not read CityJSON {cm.get_version()}")
    cm.decompress()
    return cm.j


def surfaces(boundaries, depth):
    if depth == 0:
        return list(boundaries)
    return [s for b in boundaries for s in surfaces(b, depth - 1)]


def values(vals, depth):
    if vals is None:
        return None
    if depth == 0:
        return list(vals)
    return [v for b in vals for v in values(b, depth - 1)]


def main():
    j = load(sys.argv[1])
    cos = j["CityObjects"]
    verts = j["vertices"]
    objects = {}
    for k, co in cos.items():
        if co["type"] in BUILDING:
            objects[k] = {"type": co["type"], "parents": co.get("parents", []),
                          "attributes": co.get("attributes", {})}

    def root(k):
        while cos[k].get("parents"):
            k = cos[k]["parents"][0]
        return k

    def lod(g):
        s = str(g["lod"])
        return s, int(s.split(".")[0])

    level = {}
    for k in objects:
        for g in cos[k].get("geometry", []):
            if g["type"] in SURFACES and lod(g)[1] in (1, 2, 3):
                r = root(k)
                level[r] = max(level.get(r, 0), lod(g)[1])
    semantic, polygons, total = {}, 0, [0.0, 0.0, 0.0]
    for k in objects:
        pick = level.get(root(k))
        cands = [(lod(g)[0], -i, g) for i, g in enumerate(cos[k].get("geometry", []))
                 if g["type"] in SURFACES and lod(g)[1] == pick]
        if not cands:
            continue
        g = max(cands, key=lambda c: (c[0], c[1]))[2]
        depth = SURFACES[g["type"]]
        for s in g.get("semantics", {}).get("surfaces", []):
            semantic[s["type"]] = semantic.get(s["type"], 0) + 1
        for surf in surfaces(g["boundaries"], depth):
            polygons += 1
            for ring in surf:
                idx = list(ring)
                if len(idx) > 1 and idx[0] == idx[-1]:
                    idx.pop()
                for i in idx:
                    for a in range(3):
                        total[a] += verts[i][a]
    json.dump({"objects": objects, "semantic": semantic, "polygons": polygons,
               "coord_sum": total}, sys.stdout)


if __name__ == "__main__":
    main()
