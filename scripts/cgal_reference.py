#!/usr/bin/env python3
"""Independent CGAL reference triangulation of every surface patch in CityGML files.

For each input .gml file this writes <out>/<stem>.json with one record per GML
surface patch (gml:Polygon, gml:Triangle, gml:PolygonPatch, gml:Rectangle, in
document order) holding the triangle count, 3D area, projected area and
planarity of a CGAL constrained Delaunay triangulation of that patch. gs4city's
own triangulation (spade) is compared against these files by a Rust test.

Usage:
    python3 scripts/cgal_reference.py [--out tests/reference/cgal] [--runs 3] [FILES_OR_DIRS...]

Defaults: <repo>/../shared/data/citygml (or $GS4CITY_SHARED/data/citygml) and
<repo>/data. Directories are searched recursively for *.gml.

Method per patch (float64 throughout):
  1. rings = exterior + interiors; the closing duplicate point is dropped.
  2. all points minus the first exterior vertex (local origin).
  3. Newell normal of the exterior ring; ~0 length -> skipped "degenerate: zero area".
  4. planarity = max |distance| of all vertices to the plane through the
     exterior-vertex centroid with that normal.
  5. project to an orthonormal (u, v) basis of the plane (u, v, n right-handed);
     consecutive duplicates (exact 3D equality, also last==first) are removed;
     a ring with < 3 distinct points -> skipped.
  6. CGAL CDT of all ring edges; a face is kept iff its centroid is inside by
     the even-odd rule over all rings. If CGAL inserted vertices (intersecting
     constraints) or raised, the patch is skipped with the reason.
  7. area = sum of 3D areas of kept triangles, using the original 3D points;
     area_projected = |shoelace(exterior)| - sum |shoelace(hole)| in (u, v).
"""
import argparse
import hashlib
import importlib.metadata
import json
import math
import os
import re
import sys
import time
import xml.etree.ElementTree as ET

from CGAL.CGAL_Kernel import Point_2
from CGAL.CGAL_Triangulation_2 import Constrained_Delaunay_triangulation_2

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GENERATOR = "scripts/cgal_reference.py"
PATCH_TYPES = {"Polygon", "Triangle", "PolygonPatch", "Rectangle"}
EXTERIOR = {"exterior", "outerBoundaryIs"}
INTERIOR = {"interior", "innerBoundaryIs"}
# Relative threshold for a "zero" Newell normal: |n| (= 2*area) compared with
# the squared bounding-box diagonal of the ring.
ZERO_AREA_REL = 1e-12

try:
    CGAL_VERSION = importlib.metadata.version("cgal")
except importlib.metadata.PackageNotFoundError:  # pragma: no cover
    CGAL_VERSION = "unknown"


def split_tag(tag):
    if tag.startswith("{"):
        ns, local = tag[1:].split("}", 1)
        return ns, local
    return "", tag


def is_gml(ns):
    return ns.startswith("http://www.opengis.net/gml")


def round_sig(x, sig=12):
    if x is None:
        return None
    if x == 0 or not math.isfinite(x):
        return 0.0 if x == 0 else x
    return float(f"{x:.{sig}g}")


# --------------------------------------------------------------------------- parsing

def _points_from_values(vals, dim):
    if dim not in (2, 3):
        raise ValueError(f"unsupported srsDimension {dim}")
    if len(vals) % dim:
        raise ValueError(f"{len(vals)} coordinates not a multiple of srsDimension {dim}")
    pts = []
    for i in range(0, len(vals), dim):
        if dim == 3:
            pts.append((vals[i], vals[i + 1], vals[i + 2]))
        else:
            pts.append((vals[i], vals[i + 1], 0.0))
    return pts


def _parse_coordinates(text, cs=",", ts=None, decimal="."):
    """GML 2 style gml:coordinates: tuples separated by ts (default whitespace)."""
    pts = []
    text = text.strip()
    if not text:
        return pts
    tuples = text.split(ts) if ts and ts.strip() else text.split()
    for t in tuples:
        t = t.strip()
        if not t:
            continue
        parts = [p.strip() for p in t.split(cs)]
        if decimal != ".":
            parts = [p.replace(decimal, ".") for p in parts]
        vals = [float(p) for p in parts if p]
        if len(vals) == 2:
            vals.append(0.0)
        pts.append(tuple(vals[:3]))
    return pts


def iter_patches(path):
    """Yield dicts {ordinal, id, type, rings: [[(x,y,z),...], ...], error} in document order.

    rings[0] is the exterior ring (may be missing -> error)."""
    dim_stack = []  # srsDimension inherited from ancestors (None = not set)
    patch = None  # current patch being collected
    ring_kind = None  # 'ext' / 'int' while inside exterior/interior
    ring_pts = None  # points of the current LinearRing
    ordinal = 0
    for event, elem in ET.iterparse(path, events=("start", "end")):
        ns, local = split_tag(elem.tag)
        if event == "start":
            d = elem.get("srsDimension") or elem.get("dimension")
            dim_stack.append(int(d) if d else (dim_stack[-1] if dim_stack else None))
            if not is_gml(ns):
                continue
            if local in PATCH_TYPES and patch is None:
                patch = {"ordinal": ordinal, "type": local,
                         "id": elem.get("{http://www.opengis.net/gml}id")
                         or elem.get("{http://www.opengis.net/gml/3.2}id"),
                         "exterior": None, "interiors": [], "error": None}
                ordinal += 1
            elif patch is not None and local in EXTERIOR:
                ring_kind = "ext"
            elif patch is not None and local in INTERIOR:
                ring_kind = "int"
            elif patch is not None and ring_kind and local in ("LinearRing", "Ring"):
                ring_pts = []
            continue

        # end event
        dim = dim_stack.pop()
        if patch is None or not is_gml(ns):
            if patch is None:
                elem.clear()
            continue
        if ring_pts is not None and local in ("pos", "posList", "coordinates"):
            text = elem.text or ""
            try:
                if local == "coordinates":
                    ring_pts.extend(_parse_coordinates(
                        text, elem.get("cs", ","), elem.get("ts"), elem.get("decimal", ".")))
                else:
                    vals = [float(v) for v in text.split()]
                    if local == "pos":
                        d = dim or len(vals)
                    else:
                        d = dim or 3
                    ring_pts.extend(_points_from_values(vals, d))
            except ValueError as e:
                patch["error"] = f"parse error: {e}"
        elif local in ("LinearRing", "Ring") and ring_pts is not None:
            if ring_kind == "ext":
                if patch["exterior"] is None:
                    patch["exterior"] = ring_pts
                else:
                    patch["error"] = "parse error: more than one exterior ring"
            elif ring_kind == "int":
                patch["interiors"].append(ring_pts)
            ring_pts = None
        elif local in EXTERIOR or local in INTERIOR:
            ring_kind = None
        elif local in PATCH_TYPES and patch is not None and local == patch["type"]:
            yield patch
            patch = None
            elem.clear()


# --------------------------------------------------------------------------- geometry

def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def norm(a):
    return math.sqrt(dot(a, a))


def newell(ring):
    nx = ny = nz = 0.0
    n = len(ring)
    for i in range(n):
        x0, y0, z0 = ring[i]
        x1, y1, z1 = ring[(i + 1) % n]
        nx += (y0 - y1) * (z0 + z1)
        ny += (z0 - z1) * (x0 + x1)
        nz += (x0 - x1) * (y0 + y1)
    return (nx, ny, nz)


def plane_basis(n):
    """Orthonormal u, v with (u, v, n) right-handed; u from the axis least aligned with n."""
    ax = min(range(3), key=lambda i: abs(n[i]))
    a = [0.0, 0.0, 0.0]
    a[ax] = 1.0
    u = cross(n, tuple(a))
    lu = norm(u)
    u = (u[0] / lu, u[1] / lu, u[2] / lu)
    v = cross(n, u)
    return u, v


def shoelace(r2):
    s = 0.0
    n = len(r2)
    for i in range(n):
        x0, y0 = r2[i]
        x1, y1 = r2[(i + 1) % n]
        s += x0 * y1 - x1 * y0
    return 0.5 * s


def dedupe_consecutive(ring3, ring2):
    """Remove consecutive duplicates (exact 3D equality), including last == first."""
    o3, o2 = [], []
    for p3, p2 in zip(ring3, ring2):
        if o3 and o3[-1] == p3:
            continue
        o3.append(p3)
        o2.append(p2)
    while len(o3) > 1 and o3[-1] == o3[0]:
        o3.pop()
        o2.pop()
    return o3, o2


def inside_even_odd(x, y, edges):
    """Crossing-number test; edges = list of (x0, y0, x1, y1) of all rings."""
    c = False
    for x0, y0, x1, y1 in edges:
        if (y0 > y) != (y1 > y):
            xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
            if x < xi:
                c = not c
    return c


def prepare(patch):
    """Everything before the CDT. Returns a record; rec['tri'] holds the CDT input or None."""
    ext = patch["exterior"]
    holes = patch["interiors"]
    rings = ([ext] if ext is not None else []) + holes
    rings = [r[:-1] if len(r) > 1 and r[-1] == r[0] else list(r) for r in rings]
    rec = {"ordinal": patch["ordinal"], "id": patch["id"], "rings": len(rings),
           "points": sum(len(r) for r in rings), "status": "ok", "reason": None,
           "triangles": 0, "area": 0.0, "area_projected": None, "planarity": None,
           "tri": None}
    if patch["type"] != "Polygon":
        rec["type"] = patch["type"]
    if patch["error"]:
        rec.update(status="skipped", reason=patch["error"])
        return rec
    if ext is None:
        rec.update(status="skipped", reason="parse error: no exterior ring")
        return rec
    if not rings[0]:
        rec.update(status="skipped", reason="degenerate: fewer than 3 distinct points")
        return rec
    o = rings[0][0]
    rings = [[sub(p, o) for p in r] for r in rings]
    n = newell(rings[0])
    ln = norm(n)
    xs = [p[0] for p in rings[0]]
    ys = [p[1] for p in rings[0]]
    zs = [p[2] for p in rings[0]]
    diag2 = (max(xs) - min(xs)) ** 2 + (max(ys) - min(ys)) ** 2 + (max(zs) - min(zs)) ** 2
    if ln == 0.0 or ln <= ZERO_AREA_REL * diag2:
        rec.update(status="skipped", reason="degenerate: zero area", area_projected=0.0)
        return rec
    n = (n[0] / ln, n[1] / ln, n[2] / ln)
    m = len(rings[0])
    c = (sum(xs) / m, sum(ys) / m, sum(zs) / m)
    rec["planarity"] = max(abs(dot(sub(p, c), n)) for r in rings for p in r)
    u, v = plane_basis(n)
    rings3, rings2 = [], []
    for r in rings:
        r2 = [(dot(p, u), dot(p, v)) for p in r]
        r3, r2 = dedupe_consecutive(r, r2)
        rings3.append(r3)
        rings2.append(r2)
    if any(len(r) < 3 for r in rings3):
        rec.update(status="skipped", reason="degenerate: fewer than 3 distinct points")
        return rec
    a_ext = abs(shoelace(rings2[0]))
    rec["area_projected"] = a_ext - sum(abs(shoelace(r)) for r in rings2[1:])
    # 2D point -> original 3D point; count distinct 3D points sharing a 2D position
    lift = {}
    merged = 0
    for r3, r2 in zip(rings3, rings2):
        for p3, p2 in zip(r3, r2):
            q = lift.get(p2)
            if q is None:
                lift[p2] = p3
            elif q != p3:
                merged += 1
    if merged:
        rec["note"] = f"{merged} distinct 3D input points share a 2D projection; CGAL merged them"
    edges = []
    for r2 in rings2:
        k = len(r2)
        for i in range(k):
            a, b = r2[i], r2[(i + 1) % k]
            edges.append((a[0], a[1], b[0], b[1]))
    rec["tri"] = (rings2, edges, lift)
    return rec


def triangulate(rings2, edges):
    """CGAL CDT of all ring edges + even-odd centroid filter. Returns (kept faces, n_vertices).

    This is the part that is timed."""
    cdt = Constrained_Delaunay_triangulation_2()
    for r2 in rings2:
        vh = [cdt.insert(Point_2(x, y)) for x, y in r2]
        k = len(vh)
        for i in range(k):
            cdt.insert_constraint(vh[i], vh[(i + 1) % k])
    kept = []
    for f in cdt.finite_faces():
        p0 = f.vertex(0).point()
        p1 = f.vertex(1).point()
        p2 = f.vertex(2).point()
        a = (p0.x(), p0.y())
        b = (p1.x(), p1.y())
        c = (p2.x(), p2.y())
        cx = (a[0] + b[0] + c[0]) / 3.0
        cy = (a[1] + b[1] + c[1]) / 3.0
        if inside_even_odd(cx, cy, edges):
            kept.append((a, b, c))
    return kept, cdt.number_of_vertices()


def finish(rec, kept, nverts):
    rings2, edges, lift = rec["tri"]
    if nverts != len(lift):
        rec.update(status="skipped",
                   reason=f"intersecting constraints: CGAL inserted {nverts - len(lift)} vertices")
        return
    area = 0.0
    for a, b, c in kept:
        pa, pb, pc = lift[a], lift[b], lift[c]
        area += 0.5 * norm(cross(sub(pb, pa), sub(pc, pa)))
    rec["triangles"] = len(kept)
    rec["area"] = area


# --------------------------------------------------------------------------- driver

def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def process_file(path, runs=3):
    t0 = time.perf_counter()
    recs = []
    holes = 0
    for patch in iter_patches(path):
        holes += len(patch["interiors"])
        recs.append(prepare(patch))
    work = [r for r in recs if r["tri"] is not None]
    best = math.inf
    best_cpu = math.inf
    results = None
    for _ in range(max(1, runs)):
        out = []
        cs = time.process_time()
        ts = time.perf_counter()
        for r in work:
            rings2, edges, _ = r["tri"]
            try:
                out.append(triangulate(rings2, edges))
            except Exception as e:  # CGAL raised
                out.append(e)
        best = min(best, time.perf_counter() - ts)
        best_cpu = min(best_cpu, time.process_time() - cs)
        results = out
    for r, res in zip(work, results):
        if isinstance(res, Exception):
            r.update(status="skipped", reason=f"CGAL error: {type(res).__name__}: {res}")
        else:
            finish(r, *res)
    polys = []
    for r in recs:
        r.pop("tri")
        for k in ("area", "area_projected", "planarity"):
            r[k] = round_sig(r[k])
        polys.append(r)
    doc = {"file": os.path.relpath(os.path.abspath(path), REPO), "sha256": sha256(path),
           "generator": GENERATOR, "cgal": CGAL_VERSION, "patches": len(polys), "holes": holes,
           "seconds_triangulate": round_sig(best, 6),
           "seconds_triangulate_cpu": round_sig(best_cpu, 6), "polygons": polys}
    wall = time.perf_counter() - t0
    return doc, wall


def default_inputs():
    shared = os.environ.get("GS4CITY_SHARED")
    cands = [os.path.join(shared, "data", "citygml")] if shared else []
    cands += [os.path.join(REPO, "..", "shared", "data", "citygml"),
              os.path.join(REPO, "shared", "data", "citygml")]
    out = [next((c for c in cands if os.path.isdir(c)), cands[0])]
    if os.path.isdir(os.path.join(REPO, "data")):
        out.append(os.path.join(REPO, "data"))
    return out


def collect(inputs):
    files = []
    for p in inputs:
        if os.path.isdir(p):
            for root, dirs, names in os.walk(p):
                dirs.sort()
                files += [os.path.join(root, n) for n in sorted(names) if n.lower().endswith(".gml")]
        elif os.path.isfile(p):
            files.append(p)
        else:
            print(f"warning: {p} does not exist, skipped", file=sys.stderr)
    seen, uniq = set(), []
    for f in files:
        a = os.path.realpath(f)
        if a not in seen:
            seen.add(a)
            uniq.append(f)
    return uniq


def summarize(doc):
    skipped = {}
    for p in doc["polygons"]:
        if p["status"] != "ok":
            key = re.sub(r"\d+", "N", p["reason"])
            skipped[key] = skipped.get(key, 0) + 1
    return skipped


def sources_counts(files):
    """(polygons, holes) per stem from the SOURCES.md tables next to the inputs, if any."""
    counts = {}
    seen = set()
    for f in files:
        d = os.path.dirname(os.path.abspath(f))
        for cand in (d, os.path.dirname(d), os.path.dirname(os.path.dirname(d))):
            p = os.path.join(cand, "SOURCES.md")
            if p in seen or not os.path.isfile(p):
                continue
            seen.add(p)
            header = None
            with open(p, encoding="utf-8") as fh:
                for line in fh:
                    if not line.startswith("|"):
                        header = None
                        continue
                    cells = [c.strip() for c in line.strip().strip("|").split("|")]
                    if "polygons" in cells and "holes" in cells:
                        header = cells
                        continue
                    if header and len(cells) == len(header) and not cells[0].startswith("-"):
                        stem = os.path.splitext(cells[0])[0]
                        try:
                            counts[stem] = (int(cells[header.index("polygons")]),
                                            int(cells[header.index("holes")]))
                        except ValueError:
                            pass
    return counts


def write_readme(args, files, summary, total_wall, load0, load1):
    import platform
    src = sources_counts(files)
    cmd = "python3 scripts/cgal_reference.py" + \
        ("" if args.out == os.path.join(REPO, "tests", "reference", "cgal")
         else f" --out {os.path.relpath(args.out, REPO)}") + \
        ("" if args.runs == 3 else f" --runs {args.runs}") + " --readme" + \
        "".join(f" {os.path.relpath(os.path.abspath(i), REPO)}" for i in args.inputs)
    L = []
    L.append("# CGAL reference triangulations of the CityGML test data\n")
    L.append("Generated by `scripts/cgal_reference.py` (do not edit by hand). One JSON per input "
             "CityGML file, named after the file stem. Each holds one record per GML surface patch "
             "(`gml:Polygon`, `gml:Triangle`, `gml:PolygonPatch`, `gml:Rectangle`, every element in "
             "document order; xlink references are not patches), triangulated independently of "
             "gs4city with a CGAL constrained Delaunay triangulation (PyPI `cgal` SWIG bindings). "
             "A Rust test compares gs4city's own triangulation (spade) against them.\n")
    L.append("## Regenerate\n")
    L.append("```\n" + cmd + "\n```\n")
    L.append(f"- CGAL Python package `cgal` {CGAL_VERSION}; Python {platform.python_version()}; "
             f"{os.cpu_count()} CPUs; load average {load0[0]:.2f} at start, {load1[0]:.2f} at end.")
    L.append("- Sanity tests: `python3 scripts/test_cgal_reference.py`.\n")
    L.append("## Record format\n")
    L.append("Top level: `file` (path relative to the repo root), `sha256`, `generator`, `cgal`, "
             "`patches`, `holes` (interior rings), `seconds_triangulate` (best of the timing runs, "
             "CDT + face filter only, wall clock), `seconds_triangulate_cpu` (same, process CPU time), "
             "`polygons` (list).\n")
    L.append("Per patch: `ordinal` (0,1,2,... over the patch elements of the file), `id` (gml:id or null), "
             "`rings` (1 + holes), `points` (all rings, closing duplicate dropped), `status` "
             "(`ok`/`skipped`), `reason`, `triangles`, `area` (sum of 3D areas of the kept triangles, "
             "original 3D vertices), `area_projected` (|shoelace exterior| - sum |shoelace holes| in the "
             "patch plane), `planarity` (max |distance| of all vertices from the plane through the "
             "exterior-vertex mean with the exterior Newell normal). Floats have 12 significant digits.\n")
    L.append("- Skipped patches have `triangles: 0`, `area: 0.0`; `area_projected` and `planarity` are "
             "filled where they could be computed (zero-area rings: `area_projected: 0.0`, "
             "`planarity: null`).")
    L.append("- Reasons: `degenerate: zero area` (Newell normal length <= 1e-12 x squared bbox diagonal "
             "of the exterior; in this data all such rings have an exactly zero normal), "
             "`degenerate: fewer than 3 distinct points` (any ring, after removing consecutive "
             "duplicates), `intersecting constraints: CGAL inserted N vertices` (the ring edges cross; "
             "CGAL's CDT splits them at new intersection vertices instead of raising), "
             "`CGAL error: ...`, `parse error: ...`.")
    L.append("- Optional keys: `type` (only for patches that are not `gml:Polygon`), `note` (only when "
             "distinct 3D input points share one 2D projection and CGAL merged them; none in this data).")
    L.append("- Faces are kept by an even-odd centroid test over all rings (valid: no Steiner points are "
             "added; patches where CGAL added some are skipped). For every `ok` patch in this data the "
             "sum of the kept triangles' 2D areas equals `area_projected` to 1e-9 relative.")
    L.append("- Compare counts and areas, not the triangles themselves: rectangle corners are cocircular, "
             "so the Delaunay triangulation is not unique; for non-planar patches `area` then depends on "
             "the diagonal chosen (allow a tolerance of the order of `planarity` x perimeter), while "
             "`area_projected` does not.\n")
    L.append("## Per file\n")
    L.append("Times: `CDT s` = best of %d runs of the per-file triangulation loop (CDT construction + "
             "centroid filter, `time.perf_counter`), `CDT cpu s` = the same loop's best `time.process_time` "
             "(less sensitive to other load on the machine), `wall s` = the whole file (parse, projection, "
             "%d timing runs, areas, JSON). `SOURCES` = the `polygons`/`holes` columns of "
             "SOURCES.md (raw `gml:Polygon`/`gml:interior` counts).\n" % (args.runs, args.runs))
    L.append("| file | patches | holes | SOURCES polygons/holes | triangles | skipped (by reason) | CDT s | CDT cpu s | wall s |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    tot = {"n": 0, "patches": 0, "holes": 0, "triangles": 0, "cdt": 0.0, "cpu": 0.0, "wall": 0.0, "skipped": {},
           "src_p": 0, "src_h": 0}
    mismatches = []
    for s in summary:
        sc = src.get(s["stem"])
        if sc is None:
            sct = "-"
        else:
            ok = sc == (s["patches"], s["holes"])
            sct = f"{sc[0]}/{sc[1]}" + ("" if ok else " **differs**")
            if not ok:
                mismatches.append(s["stem"])
        sk = ", ".join(f"{k}: {v}" for k, v in sorted(s["skipped"].items())) or "0"
        L.append(f"| {s['stem']} | {s['patches']} | {s['holes']} | {sct} | {s['triangles']} | {sk} | "
                 f"{s['seconds_triangulate']:.4f} | {s['seconds_triangulate_cpu']:.4f} | "
                 f"{s['seconds_wall']:.3f} |")
        if "ingolstadt_north" in s["file"].replace(os.sep, "/").split("/"):
            tot["n"] += 1
            tot["src_p"] += sc[0] if sc else 0
            tot["src_h"] += sc[1] if sc else 0
            for k in ("patches", "holes", "triangles"):
                tot[k] += s[k]
            tot["cdt"] += s["seconds_triangulate"]
            tot["cpu"] += s["seconds_triangulate_cpu"]
            tot["wall"] += s["seconds_wall"]
            for k, v in s["skipped"].items():
                tot["skipped"][k] = tot["skipped"].get(k, 0) + v
    if tot["n"]:
        sk = ", ".join(f"{k}: {v}" for k, v in sorted(tot["skipped"].items())) or "0"
        L.append(f"| **ingolstadt_north, sum of {tot['n']} files** | {tot['patches']} | {tot['holes']} | "
                 f"{tot['src_p']}/{tot['src_h']} | {tot['triangles']} | {sk} | {tot['cdt']:.4f} | "
                 f"{tot['cpu']:.4f} | "
                 f"{tot['wall']:.3f} |")
    L.append("")
    L.append(f"Total wall time of the run: {total_wall:.2f} s for {len(files)} files.")
    if src:
        L.append("Patch and hole counts " + ("match SOURCES.md for every file listed there."
                                             if not mismatches else
                                             "differ from SOURCES.md for: " + ", ".join(mismatches) + "."))
    L.append("")
    with open(os.path.join(args.out, "README.md"), "w") as fh:
        fh.write("\n".join(L))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "reference", "cgal"))
    ap.add_argument("--runs", type=int, default=3, help="timing repetitions (best is kept)")
    ap.add_argument("--summary", help="also write a per-file summary JSON here")
    ap.add_argument("--readme", action="store_true",
                    help="also write <out>/README.md with the per-file table")
    ap.add_argument("inputs", nargs="*")
    args = ap.parse_args(argv)
    files = collect(args.inputs or default_inputs())
    if not files:
        print("no .gml files found", file=sys.stderr)
        return 1
    stems = {}
    for f in files:
        stem = os.path.splitext(os.path.basename(f))[0]
        if stem in stems:
            print(f"error: duplicate stem {stem}: {stems[stem]} and {f}", file=sys.stderr)
            return 1
        stems[stem] = f
    os.makedirs(args.out, exist_ok=True)
    summary = []
    load0 = os.getloadavg()
    t_all = time.perf_counter()
    for stem, f in stems.items():
        doc, wall = process_file(f, args.runs)
        with open(os.path.join(args.out, stem + ".json"), "w") as fh:
            json.dump(doc, fh, separators=(",", ":"))
            fh.write("\n")
        sk = summarize(doc)
        tris = sum(p["triangles"] for p in doc["polygons"])
        summary.append({"stem": stem, "file": doc["file"], "patches": doc["patches"],
                        "holes": doc["holes"], "triangles": tris, "skipped": sk,
                        "seconds_triangulate": doc["seconds_triangulate"],
                        "seconds_triangulate_cpu": doc["seconds_triangulate_cpu"],
                        "seconds_wall": round(wall, 3)})
        print(f"{stem}: {doc['patches']} patches, {doc['holes']} holes, {tris} triangles, "
              f"skipped {sum(sk.values())} {sk}, CDT {doc['seconds_triangulate']:.4f} s "
              f"(best of {args.runs}), wall {wall:.3f} s", flush=True)
    total_wall = time.perf_counter() - t_all
    print(f"total wall {total_wall:.2f} s for {len(files)} files")
    if args.readme:
        write_readme(args, files, summary, total_wall, load0, os.getloadavg())
    if args.summary:
        with open(args.summary, "w") as fh:
            json.dump(summary, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
