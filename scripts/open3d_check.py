#!/usr/bin/env python3
"""Cross-check gs4city's global raycasting pass against Open3D's RaycastingScene.

Usage: open3d_check.py DIR [--bench]

DIR holds .npy files written by gs4city (tests/open3d_check.rs, benches/raycast.rs):
  vertices.npy (N,3) float32, faces.npy (M,3) int32, feature.npy (M,) int32,
  rays.npy (R,6) float32 (origin, unit direction), rust_face.npy (R,) int32 (-1 = miss).
Compares hit primitive -> feature id per ray; prints `agreement <fraction> (<n> of <R> rays differ)`
and exits 0 iff agreement >= 0.9999. With --bench, also times cast_rays (best of 3) and
prints `open3d_seconds <s>` and `open3d_build_seconds <s>`.
"""
import sys
import time

import numpy as np
import open3d as o3d


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    d = sys.argv[1]
    bench = "--bench" in sys.argv[2:]
    verts = np.load(f"{d}/vertices.npy").astype(np.float32)
    faces = np.load(f"{d}/faces.npy").astype(np.uint32)
    feature = np.load(f"{d}/feature.npy").astype(np.int64)
    rays = np.load(f"{d}/rays.npy").astype(np.float32)
    rust_face = np.load(f"{d}/rust_face.npy").astype(np.int64)

    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(faces))
    rt = o3d.core.Tensor(rays)
    ans = scene.cast_rays(rt)  # the first cast builds the BVH
    build = time.perf_counter() - t0
    best = float("inf")
    if bench:
        for _ in range(3):
            t = time.perf_counter()
            ans = scene.cast_rays(rt)
            best = min(best, time.perf_counter() - t)
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    miss = prim == o3d.t.geometry.RaycastingScene.INVALID_ID
    o3d_feat = np.where(miss, -1, feature[np.where(miss, 0, prim)])
    rust_feat = np.where(rust_face < 0, -1, feature[np.maximum(rust_face, 0)])
    differ = int(np.count_nonzero(o3d_feat != rust_feat))
    n = len(rays)
    agreement = 1.0 - differ / max(n, 1)
    print(f"agreement {agreement:.6f} ({differ} of {n} rays differ; {int(np.count_nonzero(~miss))} Open3D hits)")
    if bench:
        print(f"open3d_seconds {best:.6f}")
        print(f"open3d_build_seconds {build:.6f}")
    return 0 if agreement >= 0.9999 else 1


if __name__ == "__main__":
    sys.exit(main())
