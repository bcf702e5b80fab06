#!/usr/bin/env python3
"""An independent writer of COLMAP binary models, for checking gs4city's reader.

Writes OUT/sparse/cameras.bin, images.bin and points3D.bin with Python's struct module
following COLMAP's documented binary layout (https://colmap.github.io/format.html and
src/colmap/scene/reconstruction_io.cc; all little endian):

  cameras.bin   uint64 count; per camera: int32 camera_id, int32 model_id, uint64 width,
                uint64 height, float64 params[n(model)]
  images.bin    uint64 count; per image: int32 image_id, float64 qw qx qy qz, float64 tx ty tz,
                int32 camera_id, name (bytes, NUL-terminated), uint64 num_points2D,
                per point: float64 x, float64 y, int64 point3D_id (-1: none)
  points3D.bin  uint64 count; per point: uint64 point3D_id, float64 x y z, uint8 r g b,
                float64 error, uint64 track_length, per element: int32 image_id,
                int32 point2D_idx

and OUT/expected.json: the values written, with each image's world-to-camera rotation matrix
computed here with NumPy from its (unnormalised) quaternion. Seeded; shares no code with
gs4city. Usage: python3 scripts/colmap_bin_writer.py OUT [--seed S]
"""
import argparse
import json
import os
import struct

import numpy as np

# name, COLMAP model id, parameter names (COLMAP's order)
MODELS = [
    ("SIMPLE_PINHOLE", 0, ["f", "cx", "cy"]),
    ("PINHOLE", 1, ["fx", "fy", "cx", "cy"]),
    ("SIMPLE_RADIAL", 2, ["f", "cx", "cy", "k"]),
    ("RADIAL", 3, ["f", "cx", "cy", "k1", "k2"]),
    ("OPENCV", 4, ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"]),
    ("FULL_OPENCV", 6, ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]),
]


def rotation(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    sparse = os.path.join(a.out, "sparse")
    os.makedirs(sparse, exist_ok=True)
    cameras, images, points = [], [], []
    for k, (name, mid, pnames) in enumerate(MODELS):
        w, h = int(rng.integers(200, 5000)), int(rng.integers(200, 4000))
        f = float(rng.uniform(0.5, 2.0) * w)
        vals = {"f": f, "fx": f, "fy": f * float(rng.uniform(0.95, 1.05)),
                "cx": w / 2 + float(rng.uniform(-20, 20)), "cy": h / 2 + float(rng.uniform(-20, 20))}
        for d in ["k", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]:
            vals[d] = float(rng.uniform(-0.02, 0.02))
        # Camera ids need not be 1..n nor sorted.
        cameras.append(dict(camera_id=[7, 1, 30, 2, 11, 5][k], model=name, model_id=mid,
                            width=w, height=h, params=[vals[p] for p in pnames],
                            param_names=pnames))
    names = ["a.jpg", "sub/dir/b.JPG", "c d.png", "ü.png", "e.tif", "f.jpg", "g.jpg"]
    for k, nm in enumerate(names):
        q = rng.normal(size=4) * float(rng.uniform(0.5, 2.0))  # not normalised on purpose
        t = rng.normal(0, 50, 3)
        n2d = int(rng.integers(0, 5))
        pts = [(float(rng.uniform(0, 100)), float(rng.uniform(0, 100)),
                int(rng.choice([-1, int(rng.integers(0, 2**40))]))) for _ in range(n2d)]
        images.append(dict(image_id=[3, 1, 100, 2, 50, 4, 9][k],
                           camera_id=cameras[k % len(cameras)]["camera_id"], name=nm,
                           qvec=q.tolist(), tvec=t.tolist(), rotation=rotation(q).tolist(),
                           points2d=pts))
    for k in range(9):
        track = [(int(images[int(rng.integers(0, len(images)))]["image_id"]), int(rng.integers(0, 50)))
                 for _ in range(int(rng.integers(0, 4)))]
        points.append(dict(id=int([1, 2, 2**33, 17, 5, 6, 99, 1000, 2**40 + 3][k]),
                           xyz=rng.normal(0, 100, 3).tolist(),
                           rgb=[int(c) for c in rng.integers(0, 256, 3)],
                           error=float(rng.uniform(0, 3)), track=track))
    with open(os.path.join(sparse, "cameras.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for c in cameras:
            f.write(struct.pack("<iiQQ", c["camera_id"], c["model_id"], c["width"], c["height"]))
            f.write(struct.pack("<%dd" % len(c["params"]), *c["params"]))
    with open(os.path.join(sparse, "images.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for im in images:
            f.write(struct.pack("<i4d3di", im["image_id"], *im["qvec"], *im["tvec"], im["camera_id"]))
            f.write(im["name"].encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", len(im["points2d"])))
            for x, y, pid in im["points2d"]:
                f.write(struct.pack("<ddq", x, y, pid))
    with open(os.path.join(sparse, "points3D.bin"), "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for p in points:
            f.write(struct.pack("<Q3d3Bd", p["id"], *p["xyz"], *p["rgb"], p["error"]))
            f.write(struct.pack("<Q", len(p["track"])))
            for iid, idx in p["track"]:
                f.write(struct.pack("<ii", iid, idx))
    with open(os.path.join(a.out, "expected.json"), "w") as f:
        json.dump(dict(cameras=cameras, images=images, points=points), f, indent=1)


if __name__ == "__main__":
    main()
