#!/usr/bin/env python3
"""Independent NumPy re-derivation of a simulated scene's ground-truth maps (`gs4city synth`).

Shares no code with gs4city. The simulator's rule (docs/synth.md, "GT per view") is: a pixel
takes the truth (class, instance) of the Gaussian with the largest alpha*T weight among the
Gaussians blended there front to back, or -1 where the accumulated alpha is below
`output.min_alpha`. This script re-derives that from the scene's own files only:

  point_cloud.ply        the Gaussians (INRIA layout, read with NumPy from the PLY header)
  gt/gaussians.npy       the per-Gaussian truth table (class, instance, feature, surface, part)
  sparse/0/cameras.txt   PINHOLE intrinsics        (COLMAP text layout)
  sparse/0/images.txt    world-to-camera poses     (COLMAP text layout)
  summary.json           config.output.min_alpha

with a vectorised float64 splatting of the sampled pixels under the INRIA 3DGS forward rules
(as in scripts/ref_raster.py: near plane z > 0.2, Jacobian clamp at 1.3 tan(fov/2), +0.3 px
dilation, 3-sigma radius, 16x16 tiles, alpha = min(0.99, o*exp(power)), alpha < 1/255 and
power > 0 skipped, the Gaussian that would take T below 1e-4 stops the pixel, front to back
by (depth, index); pixel (x, y) at its centre: the mean is shifted by -0.5), and compares
with gt/<stem>.class.npy and .instance.npy.

Pixels are drawn uniformly at random (seeded) per view. A sampled pixel is "interior" for a
map when its 3x3 neighbourhood in that GT map is uniform (and not on the image border); at
occlusion boundaries (non-uniform neighbourhoods) the top-1 Gaussian is decided by weights that
differ in the last f32 bits between the two implementations, so those pixels are counted but
not held to the bound. Nothing is excluded by class: sky (-1), buildings, ground, objects
(trees, cars, persons) and floaters are all Gaussians with a truth row.

Usage: python3 scripts/gt_reference.py SCENE [--views N] [--samples K] [--seed S] [--defect D]
Prints one JSON object: per view and in total, sampled / interior / agreeing pixel counts.
`--defect half-pixel` makes the re-derivation deliberately wrong (pixel centres half a pixel to the
right), to show that the bounds of tests/gt_reference.rs notice a small defect.
"""
import argparse
import json
import os
import sys

import numpy as np

TILE = 16


def read_ply(path):
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        sys.exit(f"{path}: only binary little-endian PLY is read here")
    types = {"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}
    n, props, in_vertex = 0, [], False
    for line in header:
        w = line.split()
        if w[:2] == ["element", "vertex"]:
            n, in_vertex = int(w[2]), True
        elif w[:1] == ["element"]:
            in_vertex = False
        elif w[:1] == ["property"] and in_vertex:
            props.append((w[2], types[w[1]]))
    v = np.frombuffer(data, dtype=np.dtype(props), count=n, offset=end)
    col = lambda *names: np.stack([v[k].astype(np.float64) for k in names], axis=1)
    return {
        "xyz": col("x", "y", "z"),
        "scale": np.exp(col("scale_0", "scale_1", "scale_2")),
        "rot": col("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacity": 1.0 / (1.0 + np.exp(-v["opacity"].astype(np.float64))),
    }


def read_cameras(sparse):
    cams = {}
    for line in open(os.path.join(sparse, "cameras.txt")):
        if line.startswith("#") or not line.strip():
            continue
        w = line.split()
        if w[1] != "PINHOLE":
            sys.exit(f"camera model {w[1]}: only PINHOLE is simulated")
        cams[int(w[0])] = dict(width=int(w[2]), height=int(w[3]), fx=float(w[4]),
                               fy=float(w[5]), cx=float(w[6]), cy=float(w[7]))
    views = []
    lines = [l for l in open(os.path.join(sparse, "images.txt")) if not l.startswith("#")]
    for k in range(0, len(lines), 2):
        w = lines[k].split()
        if not w:
            continue
        q = np.array(list(map(float, w[1:5])))
        qw, qx, qy, qz = q / np.linalg.norm(q)
        R = np.array([
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
        ])
        stem = os.path.splitext(w[9])[0]
        views.append(dict(stem=stem, R=R, t=np.array(list(map(float, w[5:8]))),
                          **cams[int(w[8])]))
    return views


def project(g, v, shift=0.0):
    """Screen-space Gaussians of view v: depth, mean, conic, opacity and tile rectangle."""
    W, H = v["width"], v["height"]
    fx, fy, cx, cy = v["fx"], v["fy"], v["cx"], v["cy"]
    t = g["xyz"] @ v["R"].T + v["t"]
    keep = t[:, 2] > 0.2
    idx = np.nonzero(keep)[0]
    t = t[keep]
    q = g["rot"][keep]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    r, x, y, z = q.T
    Rq = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)], -1),
        np.stack([2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)], -1),
        np.stack([2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    M = Rq * g["scale"][keep][:, None, :]
    Sigma = M @ M.transpose(0, 2, 1)
    limx, limy = 1.3 * W / (2 * fx), 1.3 * H / (2 * fy)
    tz = t[:, 2]
    txc = np.clip(t[:, 0] / tz, -limx, limx) * tz
    tyc = np.clip(t[:, 1] / tz, -limy, limy) * tz
    J = np.zeros((len(t), 2, 3))
    J[:, 0, 0] = fx / tz
    J[:, 0, 2] = -fx * txc / tz ** 2
    J[:, 1, 1] = fy / tz
    J[:, 1, 2] = -fy * tyc / tz ** 2
    T = J @ v["R"]
    cov = T @ Sigma @ T.transpose(0, 2, 1)
    a, b, c = cov[:, 0, 0] + 0.3, cov[:, 0, 1], cov[:, 1, 1] + 0.3
    det = a * c - b * b
    ok = det != 0
    det = np.where(ok, det, 1.0)
    mid = 0.5 * (a + c)
    l1 = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
    l2 = mid - np.sqrt(np.maximum(0.1, mid * mid - det))
    radius = np.ceil(3.0 * np.sqrt(np.maximum(l1, l2)))
    mx = fx * t[:, 0] / tz + cx - 0.5 - shift
    my = fy * t[:, 1] / tz + cy - 0.5
    gx, gy = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    ti = lambda u, hi: np.clip(np.trunc(u), 0, hi).astype(np.int64)
    rx0, ry0 = ti((mx - radius) / TILE, gx), ti((my - radius) / TILE, gy)
    rx1, ry1 = ti((mx + radius + TILE - 1) / TILE, gx), ti((my + radius + TILE - 1) / TILE, gy)
    ok &= (rx1 - rx0) * (ry1 - ry0) != 0
    s = np.nonzero(ok)[0]
    return dict(index=idx[s], depth=tz[s], mx=mx[s], my=my[s], ca=c[s] / det[s],
                cb=-b[s] / det[s], cc=a[s] / det[s], op=g["opacity"][idx[s]],
                rect=(rx0[s], ry0[s], rx1[s], ry1[s]))


def top1(p, px, py):
    """Per pixel (px, py): (index of the top-1 Gaussian or -1, accumulated alpha)."""
    order = np.lexsort((p["index"], p["depth"]))
    p = {k: (v[order] if k != "rect" else tuple(r[order] for r in v)) for k, v in p.items()}
    rx0, ry0, rx1, ry1 = p["rect"]
    best = np.full(len(px), -1, np.int64)
    acc = np.zeros(len(px))
    tx, ty = px // TILE, py // TILE
    for tile in sorted(set(zip(tx.tolist(), ty.tolist()))):
        cand = np.nonzero((rx0 <= tile[0]) & (tile[0] < rx1) & (ry0 <= tile[1]) & (tile[1] < ry1))[0]
        for k in np.nonzero((tx == tile[0]) & (ty == tile[1]))[0]:
            dx, dy = p["mx"][cand] - px[k], p["my"][cand] - py[k]
            power = -0.5 * (p["ca"][cand] * dx * dx + p["cc"][cand] * dy * dy) - p["cb"][cand] * dx * dy
            alpha = np.minimum(0.99, p["op"][cand] * np.exp(np.minimum(power, 0.0)))
            live = (power <= 0) & (alpha >= 1.0 / 255.0)
            al, ids = alpha[live], cand[live]
            if len(al) == 0:
                continue
            after = np.cumprod(1.0 - al)
            before = np.concatenate([[1.0], after[:-1]])
            # The Gaussian that would take T below 1e-4 stops the pixel and is not blended.
            stop = np.nonzero(after < 1e-4)[0]
            n = stop[0] if len(stop) else len(al)
            if n == 0:
                continue
            w = al[:n] * before[:n]
            best[k] = p["index"][ids[np.argmax(w)]]
            acc[k] = 1.0 - after[n - 1]
    return best, acc


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--views", type=int, default=0, help="every k-th view so that N are used (0: all)")
    ap.add_argument("--samples", type=int, default=4000, help="pixels per view")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--defect", choices=["half-pixel"])
    a = ap.parse_args()
    summary = json.load(open(os.path.join(a.scene, "summary.json")))
    min_alpha = summary["config"]["output"]["min_alpha"]
    g = read_ply(os.path.join(a.scene, "point_cloud.ply"))
    truth = np.load(os.path.join(a.scene, "gt", "gaussians.npy"))
    if truth.shape != (len(g["xyz"]), 5):
        sys.exit(f"gt/gaussians.npy has shape {truth.shape}, the PLY {len(g['xyz'])} Gaussians")
    views = read_cameras(os.path.join(a.scene, "sparse", "0"))
    if a.views and a.views < len(views):
        views = [views[round(i * (len(views) - 1) / max(1, a.views - 1))] for i in range(a.views)]
    rng = np.random.default_rng(a.seed)
    keys = ["sampled", "class_interior", "class_agree", "class_boundary", "class_boundary_agree",
            "instance_interior", "instance_agree", "instance_boundary",
            "instance_boundary_agree", "background_interior"]
    total = dict.fromkeys(keys, 0)
    per_view = {}
    for v in views:
        gt_c = np.load(os.path.join(a.scene, "gt", v["stem"] + ".class.npy"))
        gt_i = np.load(os.path.join(a.scene, "gt", v["stem"] + ".instance.npy"))
        H, W = gt_c.shape
        if (H, W) != (v["height"], v["width"]):
            sys.exit(f"{v['stem']}: GT {W}x{H}, camera {v['width']}x{v['height']}")
        flat = rng.choice(H * W, size=min(a.samples, H * W), replace=False)
        py, px = flat // W, flat % W
        best, acc = top1(project(g, v, 0.5 if a.defect == "half-pixel" else 0.0), px, py)
        hit = (best >= 0) & (acc >= min_alpha)
        cls = np.where(hit, truth[np.maximum(best, 0), 0], -1)
        ins = np.where(hit, truth[np.maximum(best, 0), 1], -1)
        row = dict.fromkeys(keys, 0)
        row["sampled"] = len(flat)
        for name, gt, mine in (("class", gt_c, cls), ("instance", gt_i, ins)):
            inner = (py > 0) & (py < H - 1) & (px > 0) & (px < W - 1)
            uniform = np.zeros(len(flat), bool)
            for k in np.nonzero(inner)[0]:
                win = gt[py[k] - 1:py[k] + 2, px[k] - 1:px[k] + 2]
                uniform[k] = (win == win[1, 1]).all()
            agree = gt[py, px] == mine
            row[f"{name}_interior"] = int(uniform.sum())
            row[f"{name}_agree"] = int((uniform & agree).sum())
            row[f"{name}_boundary"] = int((~uniform).sum())
            row[f"{name}_boundary_agree"] = int((~uniform & agree).sum())
            if name == "class":
                row["background_interior"] = int((uniform & (gt[py, px] == -1)).sum())
        per_view[v["stem"]] = row
        for k in keys:
            total[k] += row[k]
    for name in ("class", "instance"):
        total[f"{name}_agreement"] = total[f"{name}_agree"] / max(1, total[f"{name}_interior"])
    print(json.dumps({"scene": a.scene, "min_alpha": min_alpha, "views": len(views),
                      "total": total, "per_view": per_view}, indent=1))


if __name__ == "__main__":
    main()
