#!/usr/bin/env python3
"""Independent check of a `gs4city export --format 3dtiles` tileset (tests/export_3dtiles.rs).

Decodes every leaf tile of TILESET (tileset.json → content .glb: JSON and BIN chunks, accessors,
EXT_mesh_features feature ids, EXT_structural_metadata string tables) with NumPy alone, places
each splat on the globe by the chain of tile transforms (glTF Y-up → 3D Tiles Z-up, then each
4×4 from the tile up to the root), and compares it with what the run says, computed here
without the code under test:

- the expected ECEF of every exported Gaussian: its scene position from SEMANTIC_PLY, back to
  the CRS by the alignment.json formula `p_geo = origin + Rᵀ (p − t) / s`, then through PROJ's
  `cs2cs CRS EPSG:4978` (proj-bin);
- its building / surface / part gml:ids (semantic.ply's feature_id / surface_id / part_id
  columns → semantics.json) and its class name (class column → the class names of
  docs/design.md);
- with --class-colors, COLOR_0 = the class palette of docs/design.md (by hand below), made
  linear (glTF vertex colours are linear; the palette is sRGB).

Each decoded splat is matched to the nearest expected Gaussian (scipy cKDTree). Prints one JSON
object: counts, the largest match distance, the mismatches (first few), per-class counts.

Usage: tiles3d_reference.py TILESET RUN_DIR MODE CRS [--class-colors] [--select FILE]
  MODE: lift or train (the folder of semantic.ply); --select: a JSON list of the Gaussian
  indices the export should hold (default: all valid ones).
"""
import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

NAMES = ["wall", "roof", "window", "door", "ground_surface", "installation", "tree",
         "person", "car", "road", "water", "other"]
PALETTE = [[200, 180, 140], [180, 60, 50], [60, 140, 230], [240, 160, 40], [120, 100, 80],
           [170, 90, 200], [40, 160, 60], [250, 60, 160], [230, 230, 30], [90, 90, 90],
           [30, 200, 220], [255, 255, 255]]
COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}


def read_glb(path):
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert magic == 0x46546C67 and version == 2 and length == len(data), path
    jlen, jtype = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942
    return doc, data[28 + jlen:28 + jlen + blen]


def view_bytes(doc, bin_, index):
    v = doc["bufferViews"][index]
    o = v.get("byteOffset", 0)
    return bin_[o:o + v["byteLength"]]


def accessor(doc, bin_, index):
    a = doc["accessors"][index]
    raw = view_bytes(doc, bin_, a["bufferView"])
    n = COMPONENTS[a["type"]]
    arr = np.frombuffer(raw, dtype=DTYPES[a["componentType"]], count=a["count"] * n,
                        offset=a.get("byteOffset", 0))
    return arr.reshape(a["count"], n)


def strings(doc, bin_, prop, count):
    values = view_bytes(doc, bin_, prop["values"])
    offsets = np.frombuffer(view_bytes(doc, bin_, prop["stringOffsets"]), dtype=np.uint32)
    assert len(offsets) == count + 1
    return [values[offsets[i]:offsets[i + 1]].decode("utf-8") for i in range(count)]


def tiles(tile, parent):
    """(content uri, 4×4 local → ECEF) of every leaf (the inner tiles hold coarse sets merged
    from their children, not Gaussians of the run)."""
    m = parent @ np.array(tile.get("transform", np.eye(4).flatten(order="F").tolist()),
                          dtype=np.float64).reshape(4, 4, order="F")
    out = []
    if "content" in tile and not tile.get("children"):
        out.append((tile["content"]["uri"], m))
    for c in tile.get("children", []):
        out += tiles(c, m)
    return out


def read_ply(path):
    """The vertex element of a binary little-endian PLY as a structured array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    types = {"float": "<f4", "double": "<f8", "int": "<i4", "uint": "<u4", "uchar": "u1",
             "char": "i1", "short": "<i2", "ushort": "<u2"}
    fields, count = [], 0
    for line in header:
        w = line.split()
        if w[:2] == ["element", "vertex"]:
            count = int(w[2])
        elif w and w[0] == "property":
            fields.append((w[2], types[w[1]]))
        elif w and w[0] == "element" and fields:
            break
    return np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end)


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    tileset_dir, run, mode, crs = Path(args[0]), Path(args[1]), args[2], args[3]
    class_colors = "--class-colors" in sys.argv
    select = None
    if "--select" in sys.argv:
        select = json.loads(Path(sys.argv[sys.argv.index("--select") + 1]).read_text())

    # The run's truth.
    ply = read_ply(run / mode / "semantic.ply")
    ents = json.loads((run / "citymodel/semantics.json").read_text())["entities"]
    gml = {e["id"]: e["object_id"] for e in ents}
    al = json.loads((run / "citymodel/alignment.json").read_text())
    pos = np.stack([ply["x"], ply["y"], ply["z"]], axis=1).astype(np.float64)
    idx = np.arange(len(ply)) if select is None else np.array(sorted(select), dtype=np.int64)
    idx = idx[np.all(np.isfinite(pos[idx]), axis=1)]
    r = np.array(al["rotation"], dtype=np.float64)
    geo = np.array(al["origin"]) + (pos[idx] - np.array(al["translation"])) @ r / al["scale"]
    text = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in geo) + "\n"
    out = subprocess.run(["cs2cs", "-f", "%.6f", crs, "EPSG:4978"], input=text,
                         capture_output=True, text=True, check=True).stdout
    expected = np.array([[float(v) for v in line.split()[:3]] for line in out.splitlines()])
    assert expected.shape == (len(idx), 3)

    # The tileset.
    tileset = json.loads((tileset_dir / "tileset.json").read_text())
    y_up_to_z_up = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]],
                            dtype=np.float64)
    ecef, ids, cats, colors = [], [], [], []
    for uri, m in tiles(tileset["root"], np.eye(4)):
        doc, bin_ = read_glb(tileset_dir / uri)
        prim = doc["meshes"][0]["primitives"][0]
        assert prim["mode"] == 0
        p = accessor(doc, bin_, prim["attributes"]["POSITION"]).astype(np.float64)
        h = np.hstack([p, np.ones((len(p), 1))])
        ecef.append((h @ (m @ y_up_to_z_up).T)[:, :3])
        colors.append(accessor(doc, bin_, prim["attributes"]["COLOR_0"])[:, :3])
        meta = doc.get("extensions", {}).get("EXT_structural_metadata", {})
        tables = meta.get("propertyTables", [])
        per = {"building": [""] * len(p), "surface": [""] * len(p), "part": [""] * len(p),
               "category": ["none"] * len(p)}
        for f in prim.get("extensions", {}).get("EXT_mesh_features", {}).get("featureIds", []):
            fid = accessor(doc, bin_, prim["attributes"][f"_FEATURE_ID_{f['attribute']}"])[:, 0]
            t = tables[f["propertyTable"]]
            col = "name" if t["class"] == "category" else "gml_id"
            names = strings(doc, bin_, t["properties"][col], t["count"])
            per[f["label"]] = ["" if v == f["nullFeatureId"] else names[int(v)] for v in fid]
            if f["label"] == "category":
                per["category"] = ["none" if v == f["nullFeatureId"] else names[int(v)]
                                   for v in fid]
        ids += list(zip(per["building"], per["surface"], per["part"]))
        cats += per["category"]
    ecef = np.vstack(ecef)
    colors = np.vstack(colors)

    # Match and compare.
    tree = cKDTree(expected)
    dist, near = tree.query(ecef, k=4)
    name = lambda e: gml.get(int(e), "") if e >= 0 else ""
    mismatches, worst, nbad = [], 0.0, 0
    matched = np.zeros(len(idx), dtype=bool)
    for s in range(len(ecef)):
        ok = False
        for d, j in zip(dist[s], near[s]):
            if d > max(dist[s][0], 0.0) + 1e-4:
                break
            g = idx[j]
            want = (name(ply["feature_id"][g]), name(ply["surface_id"][g]),
                    name(ply["part_id"][g]))
            cls = int(ply["class"][g])
            want_cat = NAMES[cls] if cls >= 0 else "none"
            color_ok = True
            if class_colors:
                srgb = np.array(PALETTE[cls] if cls >= 0 else [0, 0, 0]) / 255.0
                # glTF vertex colours are linear: the sRGB transfer function undone.
                rgb = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
                color_ok = bool(np.all(np.abs(colors[s] - rgb) < 1e-3))
            if ids[s] == want and cats[s] == want_cat and color_ok:
                ok = True
                matched[j] = True
                break
        worst = max(worst, float(dist[s][0]))
        nbad += 0 if ok else 1
        if not ok and len(mismatches) < 10:
            g = idx[near[s][0]]
            mismatches.append({"splat": s, "distance": float(dist[s][0]), "got": ids[s],
                               "category": cats[s], "gaussian": int(g),
                               "want": [name(ply["feature_id"][g]), name(ply["surface_id"][g]),
                                        name(ply["part_id"][g])],
                               "class": int(ply["class"][g]), "color": colors[s].tolist()})
    result = {
        "splats": int(len(ecef)),
        "expected": int(len(idx)),
        "max_distance_m": worst,
        "mismatches": mismatches,
        "mismatch_count": nbad,
        "unmatched_expected": int(np.sum(~matched)),
        "categories": {c: cats.count(c) for c in sorted(set(cats))},
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
