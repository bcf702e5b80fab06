#!/usr/bin/env python3
"""Checks a SIMULATED scene's per-Gaussian truth (`gs4city synth`: gt/gaussians.npy) against geometry.

Shares no code with gs4city. Every simulated metric rests on the truth table (int32 N x 5: class,
instance, feature, surface, part per Gaussian of point_cloud.ply); this script checks it against the
scene's own files, read independently:

  citymodel/*.gml   the CityGML handed over (byte copies of the inputs, index-prefixed: sorted
                    order = input order), read with ElementTree; every patch triangulated with
                    CGAL by scripts/cgal_reference.py's functions (the CGAL reference meshes)
  summary.json      alignment_true (geo -> scene frame), config.splats.recess, objects[].shapes
                    (the solids each tree/car/person was drawn in, from its own parameters)
  point_cloud.ply   the Gaussians' centres (f32)
  gt/instances.json the entity table's gml:ids and classes (checked against this reader's)

Rules checked (docs/synth.md, docs/design.md, src/classes.rs's documented mapping):

* Entity ids are the understood city objects (Building, BuildingPart, BuildingInstallation,
  BuildingConstructiveElement, the six thematic surfaces, Window, Door, WindowSurface, DoorSurface)
  in document order over the files in sorted order. A patch belongs to the innermost object around
  it and counts when its LoD (the lodN... property around it) is its building's: 3, else 2, else 1.
* Every city row (0 <= instance < 1 000 000): feature/surface/part = the entity's chain (a feature
  resets the chain, a surface sets surface and clears part, a part sets part), instance = the finest
  valid level, class = window/door for openings, installation for anything under an installation,
  roof for Roof/OuterFloorSurface, ground_surface for GroundSurface, wall otherwise.
* Geometry, on a seeded sample of city Gaussians: the distance (f64, brute force over the CGAL
  triangles, closest point on each triangle) from the Gaussian's centre to the surface of its
  instance entity (every patch whose owner has that instance) is at most --tol metres (x scale),
  plus the recess (config.splats.recess x scale) for windows and doors, which the simulator moves
  behind their wall. Patches CGAL cannot triangulate without new vertices (crossing rings) are
  measured on their plane instead (even-odd inside test, else distance to the ring edges).
* Objects: every Gaussian of instance >= 1 000 010 lies (within --tol) in one of its object's
  shapes (mapped to the scene frame), its class is the object's, and each object has as many
  Gaussians as summary.json says; road/pavement/grass rows are class road, water rows water,
  floater rows other.

Usage: python3 scripts/truth_geometry.py SCENE [--samples K] [--seed S] [--tol M] [--truth NPY]
Prints one JSON object; exit 0 when it could read everything (the caller judges the counts).
"""
import argparse
import glob
import json
import math
import os
import re
import sys
import xml.etree.ElementTree as ET

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cgal_reference as cr  # noqa: E402  (CGAL triangulation of one patch)
from gt_reference import read_ply  # noqa: E402  (the binary PLY reader of the references)

FEATURE = {"Building", "BuildingPart", "BuildingInstallation", "BuildingConstructiveElement"}
SURFACE = {"WallSurface", "RoofSurface", "GroundSurface", "ClosureSurface",
           "OuterCeilingSurface", "OuterFloorSurface"}
PART = {"Window", "Door", "WindowSurface", "DoorSurface"}
CLASSES = FEATURE | SURFACE | PART
# Evaluation class ids (docs/design.md).
WALL, ROOF, WINDOW, DOOR, GROUND_SURFACE, INSTALLATION = 0, 1, 2, 3, 4, 5
NAMES = ["wall", "roof", "window", "door", "ground_surface", "installation", "tree", "person",
         "car", "road", "water", "other"]
FIRST_INSTANCE = 1_000_000
ROAD, PAVEMENT, GRASS, WATER, FLOATERS = range(FIRST_INSTANCE, FIRST_INSTANCE + 5)
FIRST_OBJECT = FIRST_INSTANCE + 10
LOD = re.compile(r"^lod([0-4])")


def read_citygml(path, ents, fi):
    """Appends the file's understood objects to `ents` (dicts) and returns its patches:
    (owner entity id or None, LoD or None, patch dict as cgal_reference.iter_patches makes)."""
    patches = []
    obj_stack, lod_stack, dim_stack = [], [], []
    patch = ring_kind = ring_pts = None
    for event, elem in ET.iterparse(path, events=("start", "end")):
        ns, local = cr.split_tag(elem.tag)
        if event == "start":
            d = elem.get("srsDimension") or elem.get("dimension")
            dim_stack.append(int(d) if d else (dim_stack[-1] if dim_stack else None))
            m = LOD.match(local) if not cr.is_gml(ns) else None
            lod_stack.append(int(m.group(1)) if m else (lod_stack[-1] if lod_stack else None))
            is_obj = local in CLASSES and ns.startswith("http://www.opengis.net/citygml")
            if is_obj:
                ents.append({"cls": local, "parent": obj_stack[-1][0] if obj_stack else None,
                             "gml_id": elem.get("{http://www.opengis.net/gml}id")
                             or elem.get("{http://www.opengis.net/gml/3.2}id"),
                             "file": fi})
            obj_stack.append((len(ents) - 1 if is_obj else (obj_stack[-1][0] if obj_stack else None),
                              is_obj))
            if cr.is_gml(ns):
                if local in cr.PATCH_TYPES and patch is None:
                    patch = {"ordinal": len(patches), "type": local, "id": None,
                             "exterior": None, "interiors": [], "error": None,
                             "owner": obj_stack[-1][0], "lod": lod_stack[-1]}
                elif patch is not None and local in cr.EXTERIOR:
                    ring_kind = "ext"
                elif patch is not None and local in cr.INTERIOR:
                    ring_kind = "int"
                elif patch is not None and ring_kind and local in ("LinearRing", "Ring"):
                    ring_pts = []
            continue
        dim = dim_stack.pop()
        lod_stack.pop()
        obj_stack.pop()
        if patch is not None and cr.is_gml(ns):
            if ring_pts is not None and local in ("pos", "posList", "coordinates"):
                text = elem.text or ""
                try:
                    if local == "coordinates":
                        ring_pts.extend(cr._parse_coordinates(
                            text, elem.get("cs", ","), elem.get("ts"), elem.get("decimal", ".")))
                    else:
                        vals = [float(v) for v in text.split()]
                        d = dim or (len(vals) if local == "pos" else 3)
                        ring_pts.extend(cr._points_from_values(vals, d))
                except ValueError as e:
                    patch["error"] = f"parse error: {e}"
            elif local in ("LinearRing", "Ring") and ring_pts is not None:
                if ring_kind == "ext":
                    patch["exterior"] = ring_pts if patch["exterior"] is None else patch["exterior"]
                elif ring_kind == "int":
                    patch["interiors"].append(ring_pts)
                ring_pts = None
            elif local in cr.EXTERIOR or local in cr.INTERIOR:
                ring_kind = None
            elif local == patch["type"]:
                patches.append(patch)
                patch = None
        if not obj_stack:
            elem.clear()
    return patches


def chains(ents):
    """(feature, surface, part) per entity: a feature resets the chain, a surface sets surface and
    clears part, a part sets part (parents come before children in document order)."""
    out = []
    for i, e in enumerate(ents):
        f, s, p = out[e["parent"]] if e["parent"] is not None else (-1, -1, -1)
        if e["cls"] in FEATURE:
            f, s, p = i, -1, -1
        elif e["cls"] in SURFACE:
            s, p = i, -1
        else:
            p = i
        out.append((f, s, p))
    return out


def eval_class(ents, i):
    e = ents[i]
    if e["cls"] in ("Window", "WindowSurface"):
        return WINDOW
    if e["cls"] in ("Door", "DoorSurface"):
        return DOOR
    x = i
    while x is not None:
        if ents[x]["cls"] in ("BuildingInstallation", "BuildingConstructiveElement"):
            return INSTALLATION
        x = ents[x]["parent"]
    if e["cls"] in ("RoofSurface", "OuterFloorSurface"):
        return ROOF
    if e["cls"] == "GroundSurface":
        return GROUND_SURFACE
    return WALL


def triangulate(patch):
    """('tri', T x 3 x 3 float64 relative to the first exterior point, origin point) for a patch
    CGAL triangulates without new vertices; ('plane', rings, origin) for crossing rings (measured
    on the plane); None for a degenerate patch (gs4city skips those too)."""
    rec = cr.prepare(patch)
    if rec["tri"] is None:
        return None
    o = patch["exterior"][0]
    rings2, edges, lift = rec["tri"]
    try:
        kept, nverts = cr.triangulate(rings2, edges)
    except Exception:  # CGAL raised: measure on the plane
        nverts = -1
    if nverts != len(lift):
        rings = [[cr.sub(p, o) for p in r] for r in [patch["exterior"]] + patch["interiors"]]
        return ("plane", [np.array(r, dtype=np.float64) for r in rings], o)
    tris = np.array([[lift[a], lift[b], lift[c]] for a, b, c in kept], dtype=np.float64)
    return ("tri", tris.reshape(-1, 3, 3), o)


def point_triangle_distance(p, tri):
    """Distance from each point p (M x 3) to each triangle (T x 3 x 3): M x T, float64
    (closest point on a triangle, by regions; Ericson, Real-Time Collision Detection 5.1.5)."""
    a, b, c = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    p = p[:, None, :]
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda u, v: np.einsum("...k,...k->...", u, v)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        inside = a + ab * v[..., None] + ac * w[..., None]
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    q = inside
    cond = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    q = np.where(cond[..., None], b + (c - b) * t_bc[..., None], q)
    cond = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    q = np.where(cond[..., None], a + ac * t_ac[..., None], q)
    cond = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    q = np.where(cond[..., None], a + ab * t_ab[..., None], q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, q)
    q = np.where(np.isfinite(q), q, a)  # degenerate (zero-area) triangle: its first corner
    return np.linalg.norm(p - q, axis=-1)


def point_plane_polygon_distance(p, rings):
    """Distance from points p (M x 3) to a planar polygon with holes given by its rings (3D):
    on the Newell plane, inside by the even-odd rule -> the plane distance, else the distance to
    the nearest ring edge."""
    n = np.array(cr.newell([tuple(x) for x in rings[0]]), dtype=np.float64)
    n /= np.linalg.norm(n)
    c = rings[0].mean(axis=0)
    u, v = (np.array(x) for x in cr.plane_basis(tuple(n)))
    pl = (p - c) @ n
    px, py = (p - c) @ u, (p - c) @ v
    inside = np.zeros(len(p), bool)
    best = np.full(len(p), np.inf)
    for r in rings:
        a, b = r, np.roll(r, -1, axis=0)
        ax, ay = (a - c) @ u, (a - c) @ v
        bx, by = (b - c) @ u, (b - c) @ v
        for k in range(len(r)):
            cross = (ay[k] > py) != (by[k] > py)
            with np.errstate(divide="ignore", invalid="ignore"):
                xi = ax[k] + (py - ay[k]) * (bx[k] - ax[k]) / (by[k] - ay[k])
            inside ^= cross & (px < xi)
            ab = b[k] - a[k]
            t = np.clip(((p - a[k]) @ ab) / max(ab @ ab, 1e-300), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(p - (a[k] + t[:, None] * ab), axis=1))
    return np.where(inside, np.abs(pl), best)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--samples", type=int, default=40000, help="city Gaussians measured")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--tol", type=float, default=0.001,
                    help="metres (x scale) a centre may lie off its surface or object")
    ap.add_argument("--truth", help="truth table to check instead of SCENE/gt/gaussians.npy")
    a = ap.parse_args()
    summary = json.load(open(os.path.join(a.scene, "summary.json")))
    al = summary["alignment_true"]
    origin = np.array(al["origin"], dtype=np.float64)
    R = np.array(al["rotation"], dtype=np.float64).reshape(3, 3)
    s, t = float(al["scale"]), np.array(al["translation"], dtype=np.float64)
    to_scene = lambda local: s * (local @ R.T) + t  # local = geo - origin (metres)
    recess = float(summary["config"]["splats"]["recess"]) * s
    tol = a.tol * s

    truth = np.load(a.truth or os.path.join(a.scene, "gt", "gaussians.npy"))
    xyz = read_ply(os.path.join(a.scene, "point_cloud.ply"))["xyz"]
    if truth.shape != (len(xyz), 5):
        sys.exit(f"truth has shape {truth.shape}, the PLY {len(xyz)} Gaussians")

    # The city model, read here.
    files = sorted(glob.glob(os.path.join(a.scene, "citymodel", "*")))
    files = [f for f in files if not f.endswith(".json")]
    if not files or any(not f.lower().endswith(".gml") for f in files):
        sys.exit(f"{a.scene}/citymodel: CityGML (*.gml) files only (no --drop-openings scene)")
    ents, patches = [], []
    for fi, f in enumerate(files):
        patches.extend(read_citygml(f, ents, fi))
    chain = chains(ents)
    root = []
    for i, e in enumerate(ents):
        root.append(i if e["parent"] is None else root[e["parent"]])
    present = {}
    for p in patches:
        if p["owner"] is not None and p["lod"] is not None:
            present.setdefault(root[p["owner"]], set()).add(p["lod"])
    lod_used = {r: next((l for l in (3, 2, 1) if l in ls), None) for r, ls in present.items()}
    finest = [c[2] if c[2] >= 0 else (c[1] if c[1] >= 0 else c[0]) for c in chain]
    cls = [eval_class(ents, i) for i in range(len(ents))]

    # The entity table of the scene against this reader's.
    inst = json.load(open(os.path.join(a.scene, "gt", "instances.json")))
    table = {"checked": 0, "mismatch": []}
    for k, v in inst.items():
        i = int(k)
        if i >= FIRST_INSTANCE:
            continue
        table["checked"] += 1
        e = ents[i] if i < len(ents) else None
        if (e is None or v["citygml_class"] != e["cls"] or v["class"] != NAMES[cls[i]]
                or (e["gml_id"] is not None and v["object_id"] != e["gml_id"])):
            table["mismatch"].append({"id": i, "scene": v, "reader": e})
    table["mismatch"] = table["mismatch"][:5] + ([f"... {len(table['mismatch'])} in all"]
                                                  if len(table["mismatch"]) > 5 else [])

    # Every city row: class and chain follow from the instance.
    city = (truth[:, 1] >= 0) & (truth[:, 1] < FIRST_INSTANCE)
    rows = truth[city]
    bad_id = rows[:, 1] >= len(ents)
    ids = np.where(bad_id, 0, rows[:, 1])
    want_chain = np.array(chain, dtype=np.int64)[ids]
    want_cls = np.array(cls, dtype=np.int64)[ids]
    want_inst = np.array(finest, dtype=np.int64)[ids]
    rows_bad_class = int((bad_id | (rows[:, 0] != want_cls)).sum())
    rows_bad_chain = int((bad_id | (want_chain != rows[:, 2:5]).any(axis=1)).sum())
    rows_not_finest = int((bad_id | (want_inst != rows[:, 1])).sum())

    # Geometry of each instance: the triangles (or planar polygons) of its patches, scene frame.
    geom = {}
    skipped = 0
    for p in patches:
        o = p["owner"]
        if o is None or p["lod"] is None or lod_used.get(root[o]) != p["lod"]:
            continue
        g = triangulate(p)
        if g is None:
            skipped += 1
            continue
        kind, data, o3 = g
        off = np.array(o3, dtype=np.float64) - origin
        if kind == "tri":
            geom.setdefault(finest[o], ([], []))[0].append(to_scene(data.reshape(-1, 3) + off)
                                                           .reshape(-1, 3, 3))
        else:
            geom.setdefault(finest[o], ([], []))[1].append([to_scene(r + off) for r in data])

    # A seeded sample of city Gaussians, measured against their instance's surface.
    rng = np.random.default_rng(a.seed)
    city_idx = np.nonzero(city)[0]
    take = np.sort(rng.choice(city_idx, size=min(a.samples, len(city_idx)), replace=False))
    dist = np.full(len(take), np.inf)
    inst_of = truth[take, 1]
    for i in np.unique(inst_of):
        sel = np.nonzero(inst_of == i)[0]
        if i >= len(ents) or i not in geom:
            continue
        tris, planes = geom[i]
        p = xyz[take[sel]]
        best = np.full(len(sel), np.inf)
        if tris:
            T = np.concatenate(tris)
            step = max(1, 2_000_000 // max(1, len(T)))  # points per block: <= 2e6 pairs
            for j in range(0, len(p), step):
                best[j:j + step] = point_triangle_distance(p[j:j + step], T).min(axis=1)
        for rings in planes:
            best = np.minimum(best, point_plane_polygon_distance(p, rings))
        dist[sel] = best
    opening = np.isin(truth[take, 0], [WINDOW, DOOR]) & (truth[take, 4] >= 0)
    allowed = np.where(opening, recess + tol, tol)
    off = dist > allowed
    by_class = {}
    for c in np.unique(truth[take, 0]):
        m = truth[take, 0] == c
        by_class[NAMES[c] if 0 <= c < len(NAMES) else str(c)] = {
            "sampled": int(m.sum()), "off": int((off & m).sum()),
            "max_distance": float(dist[m].max()) if m.any() else None}
    worst = np.argsort(-(dist - allowed))[:5]
    examples = [{"gaussian": int(take[k]), "truth": truth[take[k]].tolist(),
                 "distance": float(dist[k]), "allowed": float(allowed[k])}
                for k in worst if off[k]]

    # Objects: inside their shapes; simulated stand-ins: their class.
    objs = {o["instance"]: o for o in summary["objects"]}
    obj_rows = np.nonzero(truth[:, 1] >= FIRST_OBJECT)[0]
    obj_out, obj_class, obj_unknown, counts = 0, 0, 0, {}
    obj_examples = []
    for i in np.unique(truth[obj_rows, 1]):
        sel = obj_rows[truth[obj_rows, 1] == i]
        counts[int(i)] = len(sel)
        o = objs.get(int(i))
        if o is None:
            obj_unknown += len(sel)
            continue
        obj_class += int((truth[sel, 0] != NAMES.index(o["class"])).sum())
        p = xyz[sel]
        inside = np.zeros(len(sel), bool)
        for sh in o["shapes"]:
            if "box" in sh:
                b = sh["box"]
                c = to_scene(np.array(b["centre"], dtype=np.float64))
                axes = np.array(b["axes"], dtype=np.float64) @ R.T  # rows: rotated unit axes
                half = np.array(b["half"], dtype=np.float64) * s
                inside |= (np.abs((p - c) @ axes.T) <= half + tol).all(axis=1)
            else:
                b = sh["sphere"]
                c = to_scene(np.array(b["centre"], dtype=np.float64))
                inside |= np.linalg.norm(p - c, axis=1) <= b["radius"] * s + tol
        obj_out += int((~inside).sum())
        for k in np.nonzero(~inside)[0][:2]:
            if len(obj_examples) < 5:
                obj_examples.append({"gaussian": int(sel[k]), "instance": int(i),
                                     "class": o["class"]})
    count_mismatch = [o["instance"] for o in summary["objects"]
                      if counts.get(o["instance"], 0) != o["gaussians"]]
    want_sim = {ROAD: 9, PAVEMENT: 9, GRASS: 9, WATER: 10, FLOATERS: 11}
    sim_bad = sum(int(((truth[:, 1] == k) & (truth[:, 0] != c)).sum()) for k, c in want_sim.items())
    other = ~city & ~np.isin(truth[:, 1], list(want_sim)) & (truth[:, 1] < FIRST_OBJECT)

    out = {
        "scene": a.scene, "gaussians": len(truth), "entities": len(ents),
        "patches": len(patches), "patches_skipped_degenerate": skipped,
        "entity_table": table,
        "city_rows": int(city.sum()), "city_rows_bad_class": rows_bad_class,
        "city_rows_bad_chain": rows_bad_chain, "city_rows_not_finest": rows_not_finest,
        "sampled": len(take), "tol": tol, "recess": recess,
        "unmeasured": int(np.isinf(dist).sum()),
        "off_surface": int(off.sum()), "off_surface_examples": examples,
        "max_distance": float(dist[~opening].max()) if (~opening).any() else None,
        "max_distance_openings": float(dist[opening].max()) if opening.any() else None,
        "min_distance_openings": float(dist[opening].min()) if opening.any() else None,
        "by_class": by_class,
        "objects": len(summary["objects"]), "object_gaussians": len(obj_rows),
        "objects_by_class": {c: sum(o["class"] == c for o in summary["objects"])
                             for c in ("tree", "car", "person")},
        "object_outside": obj_out, "object_outside_examples": obj_examples,
        "object_bad_class": obj_class, "object_unknown": obj_unknown,
        "object_count_mismatch": count_mismatch,
        "simulated_rows_bad_class": sim_bad, "rows_unaccounted": int(other.sum()),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
