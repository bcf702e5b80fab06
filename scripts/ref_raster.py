#!/usr/bin/env python3
"""Independent plain-NumPy reference of the INRIA 3DGS forward rasterizer (float64).

Shares no code with the Rust rasterizer. Generates small seeded test scenes that include
the hard cases (near-singular, extremely anisotropic, behind the camera, straddling the
near plane, screen-covering, opaque stacks that hit the transmittance threshold, exact
depth ties, off-screen Gaussians that exercise the Jacobian clamp) and writes into
tests/data/render/:

  <scene>.ply                 INRIA layout + extra float properties feat_0..2
  cases.json                  cameras (world->camera R row-major, t, intrinsics) + options
  <case>.<channel>.npy        golden float32 renders: rgb (H,W,3), alpha, depth_acc,
                              depth (expected, NaN where alpha < 1e-3), median (H,W),
                              features (3,H,W)

Run from the repository root: python3 scripts/ref_raster.py

Or render a given INRIA PLY (binary little-endian, float properties) from given cameras:

  python3 scripts/ref_raster.py --ply SCENE.ply --cameras CAMERAS.json --out DIR

CAMERAS.json is a list of cameras as in cases.json (name, width, height, fx, fy, cx, cy,
rotation, translation); DIR/<name>.rgb.npy and DIR/<name>.alpha.npy are written (black
background, not antialiased).
"""
import json
import os
import sys

import numpy as np

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "data", "render")

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396]
SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435]
REST = {0: 0, 1: 9, 2: 24, 3: 45}
DEPTH_MIN_ALPHA = 1e-3


# ---------------------------------------------------------------- scenes

def make_scene(seed, degree, n_random):
    rng = np.random.default_rng(seed)
    rows = []  # (xyz, dc, rest(3,K), opacity_logit, log_scale(3), quat(4), feat(3))
    K = (degree + 1) ** 2 - 1

    def add(xyz, log_scale, op, quat=None, dc=None):
        quat = rng.normal(size=4) if quat is None else np.asarray(quat, float)
        dc = rng.normal(0, 1, 3) if dc is None else np.asarray(dc, float)
        rest = rng.normal(0, 0.3, (3, K))
        feat = rng.normal(0, 1, 3)
        rows.append((np.asarray(xyz, float), dc, rest, float(op), np.asarray(log_scale, float),
                     quat, feat))

    # Plausible random Gaussians in front of the camera (camera at origin looking +z
    # after the test pose; the scene frame is the camera's frame up to the pose).
    for _ in range(n_random):
        z = rng.uniform(2.0, 8.0)
        x = rng.uniform(-0.6, 0.6) * z
        y = rng.uniform(-0.45, 0.45) * z
        add([x, y, z], rng.uniform(-4.0, -1.5, 3), rng.uniform(-3, 4))
    # Near-singular: tiny scales.
    add([0.1, 0.1, 3.0], [-25.0, -25.0, -25.0], 3.0)
    add([-0.3, 0.2, 4.0], [-30.0, -2.0, -2.0], 3.0)
    # Extremely anisotropic needles.
    add([0.2, -0.3, 5.0], [0.5, -9.0, -9.0], 2.0)
    add([-0.5, -0.2, 3.5], [-12.0, 0.3, -12.0], 2.0)
    # Behind the camera and straddling / just inside the near plane.
    add([0.0, 0.0, -2.0], [0.0, 0.0, 0.0], 5.0)
    add([0.05, 0.0, 0.15], [-1.0, -1.0, -1.0], 5.0)
    add([0.05, -0.02, 0.25], [-1.0, -1.0, -1.0], 1.0)
    add([0.3, 0.2, 0.6], [0.0, -0.5, 0.2], 0.5)
    # Huge, screen-covering.
    add([0.0, 0.0, 6.0], [2.0, 2.0, 1.0], -1.0)
    add([1.0, -0.5, 9.0], [3.0, 2.5, 2.0], -2.5)
    # Off-screen centres (Jacobian clamp) with large extent.
    add([8.0, 0.5, 3.0], [0.5, -0.5, -0.5], 2.0)
    add([-2.0, -7.0, 2.5], [-0.2, 0.8, -0.5], 2.0)
    # Opaque stack: same xy, increasing depth -> hits T < 1e-4.
    for i in range(40):
        add([-0.8, 0.5, 2.0 + 0.05 * i], [-2.0, -2.0, -2.0], 12.0)
    # Exact depth ties: identical positions, different colours (order by index).
    for _ in range(4):
        add([0.6, 0.4, 4.5], [-1.8, -1.8, -1.8], 1.5, quat=[1, 0, 0, 0])
    # Axis-aligned, unnormalised quaternion.
    add([-0.2, -0.6, 3.0], [-1.5, -2.5, -2.0], 2.0, quat=[3.0, 0.0, 0.0, 0.0])
    f32 = np.float32
    g = {
        "xyz": np.array([r[0] for r in rows], f32),
        "dc": np.array([r[1] for r in rows], f32),
        "rest": np.array([r[2] for r in rows], f32).reshape(len(rows), 3 * K),
        "opacity": np.array([r[3] for r in rows], f32),
        "scale": np.array([r[4] for r in rows], f32),
        "rot": np.array([r[5] for r in rows], f32),
        "feat": np.array([r[6] for r in rows], f32),
        "degree": degree,
    }
    return g


def write_ply(path, g):
    n = len(g["xyz"])
    K3 = g["rest"].shape[1]
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
             + [f"f_rest_{i}" for i in range(K3)] + ["opacity"]
             + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
             + [f"feat_{i}" for i in range(3)])
    data = np.concatenate([g["xyz"], np.zeros((n, 3), np.float32), g["dc"], g["rest"],
                           g["opacity"][:, None], g["scale"], g["rot"], g["feat"]], axis=1)
    assert data.shape[1] == len(names)
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join(f"property float {p}\n" for p in names) + "end_header\n"
    with open(path, "wb") as f:
        f.write(header.encode())
        f.write(data.astype("<f4").tobytes())


# ---------------------------------------------------------------- cameras

def look_at(eye, target, up):
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return R, -R @ eye


# ---------------------------------------------------------------- reference renderer

def quat_to_mat(q):
    r, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)],
        [2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)],
        [2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)],
    ])


def sh_to_rgb(degree, sh, d):
    """sh: (16 or fewer, 3) coefficient-major."""
    x, y, z = d
    res = SH_C0 * sh[0]
    if degree > 0:
        res = res - SH_C1 * y * sh[1] + SH_C1 * z * sh[2] - SH_C1 * x * sh[3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (res + SH_C2[0] * xy * sh[4] + SH_C2[1] * yz * sh[5]
                   + SH_C2[2] * (2 * zz - xx - yy) * sh[6] + SH_C2[3] * xz * sh[7]
                   + SH_C2[4] * (xx - yy) * sh[8])
            if degree > 2:
                res = (res + SH_C3[0] * y * (3 * xx - yy) * sh[9]
                       + SH_C3[1] * xy * z * sh[10]
                       + SH_C3[2] * y * (4 * zz - xx - yy) * sh[11]
                       + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[12]
                       + SH_C3[4] * x * (4 * zz - xx - yy) * sh[13]
                       + SH_C3[5] * z * (xx - yy) * sh[14]
                       + SH_C3[6] * x * (xx - 3 * yy) * sh[15])
    return np.maximum(res + 0.5, 0.0)


def render(g, cam, antialiased, background):
    W, H = cam["width"], cam["height"]
    fx, fy, cx, cy = cam["fx"], cam["fy"], cam["cx"], cam["cy"]
    Rw = np.array(cam["rotation"], float)
    tw = np.array(cam["translation"], float)
    campos = -Rw.T @ tw
    tan_fovx, tan_fovy = W / (2 * fx), H / (2 * fy)
    gx, gy = (W + 15) // 16, (H + 15) // 16
    degree = g["degree"]
    K = (degree + 1) ** 2 - 1
    feats = g["feat"].astype(float)
    vis = []
    for i in range(len(g["xyz"])):
        p = g["xyz"][i].astype(float)
        t = Rw @ p + tw
        if t[2] <= 0.2:
            continue
        s = np.exp(g["scale"][i].astype(float))
        Rq = quat_to_mat(g["rot"][i].astype(float))
        M = Rq @ np.diag(s)
        Sigma = M @ M.T
        limx, limy = 1.3 * tan_fovx, 1.3 * tan_fovy
        txc = min(limx, max(-limx, t[0] / t[2])) * t[2]
        tyc = min(limy, max(-limy, t[1] / t[2])) * t[2]
        J = np.array([[fx / t[2], 0.0, -fx * txc / t[2] ** 2],
                      [0.0, fy / t[2], -fy * tyc / t[2] ** 2]])
        cov = J @ Rw @ Sigma @ Rw.T @ J.T
        det0 = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        cov[0, 0] += 0.3
        cov[1, 1] += 0.3
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        if det == 0:
            continue
        conic = (cov[1, 1] / det, -cov[0, 1] / det, cov[0, 0] / det)
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        l1 = mid + np.sqrt(max(0.1, mid * mid - det))
        l2 = mid - np.sqrt(max(0.1, mid * mid - det))
        radius = np.ceil(3.0 * np.sqrt(max(l1, l2)))
        mx = fx * t[0] / t[2] + cx - 0.5
        my = fy * t[1] / t[2] + cy - 0.5

        def clampi(v, hi):
            return int(min(hi, max(0, int(np.trunc(v)))))
        rx0, ry0 = clampi((mx - radius) / 16, gx), clampi((my - radius) / 16, gy)
        rx1, ry1 = clampi((mx + radius + 15) / 16, gx), clampi((my + radius + 15) / 16, gy)
        if (rx1 - rx0) * (ry1 - ry0) == 0:
            continue
        op = 1.0 / (1.0 + np.exp(-float(g["opacity"][i])))
        if antialiased:
            op *= np.sqrt(max(0.000025, det0 / det))
        d = p - campos
        d /= np.linalg.norm(d)
        rest = g["rest"][i].astype(float).reshape(3, K) if K else np.zeros((3, 0))
        sh = np.concatenate([g["dc"][i].astype(float)[None, :], rest.T], axis=0)
        color = sh_to_rgb(degree, sh, d)
        vis.append((t[2], i, mx, my, conic, op, color, (rx0, ry0, rx1, ry1)))
    order = sorted(range(len(vis)), key=lambda k: (vis[k][0], vis[k][1]))
    T = np.ones((H, W))
    C = np.zeros((H, W, 3))
    F = np.zeros((3, H, W))
    D = np.zeros((H, W))
    med = np.full((H, W), np.nan)
    done = np.zeros((H, W), bool)
    for k in order:
        z, i, mx, my, (a, b, c), op, color, (rx0, ry0, rx1, ry1) = vis[k]
        x0, x1 = rx0 * 16, min(rx1 * 16, W)
        y0, y1 = ry0 * 16, min(ry1 * 16, H)
        if x0 >= x1 or y0 >= y1:
            continue
        py, px = np.mgrid[y0:y1, x0:x1].astype(float)
        dx, dy = mx - px, my - py
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = np.minimum(0.99, op * np.exp(np.minimum(power, 0.0)))
        sub = (slice(y0, y1), slice(x0, x1))
        live = ~done[sub] & (power <= 0) & (alpha >= 1.0 / 255.0)
        Ts = T[sub]
        test_T = Ts * (1 - alpha)
        stop = live & (test_T < 1e-4)
        add = live & ~stop
        done[sub] |= stop
        w = np.where(add, alpha * Ts, 0.0)
        C[sub] += w[..., None] * color[None, None, :]
        F[:, y0:y1, x0:x1] += w[None] * feats[i][:, None, None]
        D[sub] += w * z
        crossing = add & (Ts >= 0.5) & (test_T < 0.5)
        med[sub] = np.where(crossing, z, med[sub])
        T[sub] = np.where(add, test_T, Ts)
    C += T[..., None] * np.asarray(background, float)[None, None, :]
    alpha_acc = 1.0 - T
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(alpha_acc >= DEPTH_MIN_ALPHA, D / alpha_acc, np.nan)
    return {"rgb": C, "alpha": alpha_acc, "depth_acc": D, "depth": depth, "median": med,
            "features": F}


# ---------------------------------------------------------------- main

def camera(name, W, H, fx, fy, cx, cy, eye, target):
    R, t = look_at(eye, target, [0.0, -1.0, 0.0])
    return {"name": name, "width": W, "height": H, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "rotation": R.tolist(), "translation": t.tolist()}


def read_ply(path):
    """An INRIA PLY (binary little-endian, every property float) as the scene dict."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from replicate_scene import read_ply as read_rows
    _, names, data = read_rows(path)
    col = {nm: data[:, i] for i, nm in enumerate(names)}
    n = len(data)
    K3 = sum(1 for nm in names if nm.startswith("f_rest_"))
    degree = {0: 0, 9: 1, 24: 2, 45: 3}[K3]
    stack = lambda keys: np.stack([col[k] for k in keys], axis=1)
    return {
        "degree": degree,
        "xyz": stack(["x", "y", "z"]),
        "dc": stack([f"f_dc_{i}" for i in range(3)]),
        "rest": stack([f"f_rest_{i}" for i in range(K3)]) if K3 else np.zeros((n, 0), np.float32),
        "opacity": col["opacity"],
        "scale": stack([f"scale_{i}" for i in range(3)]),
        "rot": stack([f"rot_{i}" for i in range(4)]),
        "feat": np.zeros((n, 3), np.float32),
    }


def main():
    if "--ply" in sys.argv:
        arg = lambda k: sys.argv[sys.argv.index(k) + 1]
        g = read_ply(arg("--ply"))
        out = arg("--out")
        os.makedirs(out, exist_ok=True)
        for cam in json.load(open(arg("--cameras"))):
            r = render(g, cam, False, [0.0, 0.0, 0.0])
            for ch in ("rgb", "alpha"):
                np.save(os.path.join(out, f"{cam['name']}.{ch}.npy"), r[ch].astype(np.float32))
        return
    os.makedirs(OUT, exist_ok=True)
    scenes = {"mixed3": make_scene(7, 3, 300), "aa1": make_scene(11, 1, 200)}
    for name, g in scenes.items():
        write_ply(os.path.join(OUT, f"{name}.ply"), g)
    cams = [
        camera("front", 80, 64, 70.0, 70.0, 40.0, 32.0, [0, 0, 0], [0, 0, 1]),
        camera("oblique", 61, 47, 55.0, 58.0, 27.3, 25.1, [0.7, -0.4, -0.5], [0.0, 0.1, 4.0]),
    ]
    cases = [
        {"case": "mixed3_front", "scene": "mixed3", "camera": cams[0], "antialiased": False,
         "background": [0.0, 0.0, 0.0]},
        {"case": "mixed3_oblique", "scene": "mixed3", "camera": cams[1], "antialiased": False,
         "background": [0.1, 0.2, 0.3]},
        {"case": "aa1_front", "scene": "aa1", "camera": cams[0], "antialiased": True,
         "background": [1.0, 1.0, 1.0]},
    ]
    for case in cases:
        out = render(scenes[case["scene"]], case["camera"], case["antialiased"],
                     case["background"])
        for ch, arr in out.items():
            np.save(os.path.join(OUT, f"{case['case']}.{ch}.npy"), arr.astype(np.float32))
        a = out["alpha"]
        print(f"{case['case']}: coverage {np.mean(a > 1e-3):.3f}, "
              f"opaque {np.mean(a > 0.99):.3f}, rgb mean {out['rgb'].mean():.4f}",
              file=sys.stderr)
    with open(os.path.join(OUT, "cases.json"), "w") as f:
        json.dump({"generator": "scripts/ref_raster.py", "cases": cases}, f, indent=1)


if __name__ == "__main__":
    main()
