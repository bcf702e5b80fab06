#!/usr/bin/env python3
"""SIMULATED city-scale inputs for the scaling benchmark of `gs4city tile` (BENCHMARKS.md, "City
scale"): a scene folder replicated K = n×n times on a grid in the city model's ground plane.

    python3 scripts/replicate_scene.py SRC OUT K [--spacing 40] [--ply-only]

Each copy k gets the Gaussians shifted by its offset (PLY rows, all-float binary little-endian),
its views (COLMAP text; camera centres shifted, image names prefixed `r<k>_`), links to the
source's images, SAM lists, features and gt/ under the new names, and the CityGML files with
coordinates shifted and gml:ids / references suffixed `_r<k>`. The images of a copy are the
source's: the neighbouring copies are not drawn in them (a cost benchmark, not an accuracy one).
`--ply-only` writes only the replicated `point_cloud.ply` (the cut benchmark on a large PLY).
Needs numpy.
"""
import argparse
import json
import os
import re
import sys

import numpy as np


def read_ply(path):
    with open(path, "rb") as f:
        head = b""
        while not head.endswith(b"end_header\n"):
            line = f.readline()
            if not line:
                sys.exit(f"{path}: no end_header")
            head += line
        lines = head.decode().split("\n")
        n = int(next(l for l in lines if l.startswith("element vertex")).split()[2])
        props = [l.split() for l in lines if l.startswith("property")]
        if any(p[1] != "float" for p in props) or "binary_little_endian" not in head.decode():
            sys.exit(f"{path}: only all-float binary little-endian PLYs are replicated")
        data = np.fromfile(f, dtype="<f4", count=n * len(props)).reshape(n, len(props))
    return head.decode(), [p[2] for p in props], data


def ground_extent(citymodel):
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for name in os.listdir(citymodel):
        if not name.endswith(".gml"):
            continue
        text = open(os.path.join(citymodel, name), encoding="utf-8").read()
        for m in re.finditer(r"<gml:(?:posList|pos)[^>]*>([^<]+)<", text):
            v = np.array(m.group(1).split(), float).reshape(-1, 3)
            lo = np.minimum(lo, v[:, :2].min(0))
            hi = np.maximum(hi, v[:, :2].max(0))
    return lo, hi


def shift_gml(text, dx, dy, k):
    def coords(m):
        v = np.array(m.group(2).split(), float).reshape(-1, 3)
        v[:, 0] += dx
        v[:, 1] += dy
        return m.group(1) + " ".join(repr(float(x)) for x in v.ravel()) + m.group(3)

    text = re.sub(r"(<gml:(?:posList|pos|lowerCorner|upperCorner)[^>]*>)([^<]+)(<)", coords, text)
    text = re.sub(r'(gml:id=")([^"]+)(")', lambda m: f"{m.group(1)}{m.group(2)}_r{k}{m.group(3)}", text)
    text = re.sub(r'(xlink:href="#)([^"]+)(")', lambda m: f"{m.group(1)}{m.group(2)}_r{k}{m.group(3)}", text)
    text = re.sub(r"(<app:target[^>]*>#?)([^<]+)(</app:target>)",
                  lambda m: f"{m.group(1)}{m.group(2)}_r{k}{m.group(3)}", text)
    return text


def link(src, dst):
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    if not os.path.lexists(dst):
        os.symlink(os.path.abspath(src), dst)


def quat_to_r(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("k", type=int)
    ap.add_argument("--spacing", type=float, default=40.0)
    ap.add_argument("--ply-only", action="store_true")
    a = ap.parse_args()
    n = int(round(a.k ** 0.5))
    if n * n != a.k:
        sys.exit("K must be a square (1, 4, 16, …)")
    src, out = a.src, a.out
    os.makedirs(out, exist_ok=False)
    al = json.load(open(os.path.join(src, "citymodel/alignment.json")))
    R, s, t = np.array(al["rotation"]), al["scale"], np.array(al["translation"])
    lo, hi = ground_extent(os.path.join(src, "citymodel"))
    step = np.full(2, (hi - lo).max() + a.spacing)  # one step both ways: a square grid of copies
    offsets = [(i * step[0], j * step[1]) for j in range(n) for i in range(n)]
    head, props, data = read_ply(os.path.join(src, "point_cloud.ply"))
    ix, iy, iz = props.index("x"), props.index("y"), props.index("z")
    head = head.replace(f"element vertex {len(data)}\n", f"element vertex {len(data) * a.k}\n")
    head = head.replace("end_header\n", f"comment SIMULATED: replicated {a.k}x by scripts/replicate_scene.py\nend_header\n")
    with open(os.path.join(out, "point_cloud.ply"), "wb") as f:
        f.write(head.encode())
        for dx, dy in offsets:
            off = s * R @ np.array([dx, dy, 0.0])
            d = data.copy()
            d[:, ix] += off[0]
            d[:, iy] += off[1]
            d[:, iz] += off[2]
            d.tofile(f)
    if a.ply_only:
        return
    os.makedirs(os.path.join(out, "citymodel"))
    json.dump(al, open(os.path.join(out, "citymodel/alignment.json"), "w"), indent=2)
    for name in sorted(os.listdir(os.path.join(src, "citymodel"))):
        if not name.endswith(".gml"):
            continue
        text = open(os.path.join(src, "citymodel", name), encoding="utf-8").read()
        for k, (dx, dy) in enumerate(offsets):
            open(os.path.join(out, "citymodel", f"r{k}_{name}"), "w", encoding="utf-8").write(
                shift_gml(text, dx, dy, k))
    sparse = os.path.join(src, "sparse/0")
    os.makedirs(os.path.join(out, "sparse/0"))
    lines = [l for l in open(os.path.join(sparse, "images.txt")) if not l.startswith("#")]
    images = []
    for i in range(0, len(lines) - 1, 2):
        w = lines[i].split()
        if len(w) >= 10:
            images.append((np.array(w[1:5], float), np.array(w[5:8], float), w[8], w[9]))
    with open(os.path.join(out, "sparse/0/images.txt"), "w") as f:
        iid = 1
        for k, (dx, dy) in enumerate(offsets):
            off = s * R @ np.array([dx, dy, 0.0])
            for q, tv, cam, name in images:
                t2 = tv - quat_to_r(q) @ off
                f.write(f"{iid} {' '.join(repr(float(x)) for x in q)} {' '.join(repr(float(x)) for x in t2)} {cam} r{k}_{name}\n\n")
                iid += 1
    open(os.path.join(out, "sparse/0/points3D.txt"), "w").close()
    link(os.path.join(sparse, "cameras.txt"), os.path.join(out, "sparse/0/cameras.txt"))
    for k in range(a.k):
        for q, tv, cam, name in images:
            stem = os.path.splitext(name)[0]
            link(os.path.join(src, "images", name), os.path.join(out, "images", f"r{k}_{name}"))
            for sub, ext in [("masks", ".json"), ("features", ".npy")]:
                p = os.path.join(src, sub, stem + ext)
                if os.path.exists(p):
                    link(p, os.path.join(out, sub, f"r{k}_{stem}{ext}"))
            for ext in [".class.npy", ".instance.npy"]:
                p = os.path.join(src, "gt", stem + ext)
                if os.path.exists(p):
                    link(p, os.path.join(out, "gt", f"r{k}_{stem}{ext}"))
    p = os.path.join(src, "features/prompts.json")
    if os.path.exists(p):
        link(p, os.path.join(out, "features/prompts.json"))


if __name__ == "__main__":
    main()
