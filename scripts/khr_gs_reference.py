#!/usr/bin/env python3
"""A reader of `KHR_gaussian_splatting` 3D Tiles written from the extension's text alone, and
its check against the run a tileset was exported from (tests/export_3dtiles.rs).

The text followed: KhronosGroup/glTF `extensions/2.0/Khronos/KHR_gaussian_splatting/README.md`
as of commit 63770cc ("Editorial review", #2567; status Release Candidate) and its schema;
for SPZ tiles the draft `KHR_gaussian_splatting_compression_spz_2/README.md` (glTF pull
request #2531, commit 90db926) and the SPZ v2 layout it points to (Niantic's format: gzip of a
16-byte header and per-point arrays). Nothing here comes from gs4city's code; the containers
(a glb's chunks, a PLY's rows, an SPZ blob's byte layout) are read by the other reference
scripts, tiles3d_reference.py and spz_reference.py.

Every tile of TILESET is read (tileset.json → each content .glb) and checked against the text:

- the primitive's `mode` is POINTS (0); the `KHR_gaussian_splatting` object has the required
  `kernel` ("ellipse") and `colorSpace` (srgb_rec709_display or lin_rec709_display);
- the required attributes with their accessor types and component types (POSITION VEC3,
  ROTATION VEC4, SCALE VEC3, OPACITY SCALAR, SH_DEGREE_0_COEF_0 VEC3 float), one count;
  spherical-harmonic degrees complete or absent (a degree only with every lower one);
- values: SCALE "linear and MUST NOT be negative", OPACITY in [0, 1], ROTATION unit
  quaternions (x, y, z, w);
- SPZ tiles: the blob's count equals every accessor's count; OPACITY and SH_DEGREE_0_COEF_0
  come from the blob (the draft maps alphas and colours to COLOR_0, scales through exp);
- every splat lies in its tile's bounding box (padded by 3 of its largest linear scale).

Then every leaf splat is placed on the globe by the chain of tile transforms (glTF Y-up →
3D Tiles Z-up, each 4×4 up to the root) and matched to the nearest Gaussian of the run's
semantic.ply, whose expected values are computed independently: its ECEF position by the
alignment.json formula `p_geo = origin + Rᵀ (p − t) / s` and PROJ's `cs2cs CRS EPSG:4978`,
its covariance Σ = R_q diag(exp(2·log s)) R_qᵀ carried to the CRS by the alignment (Rᵀ Σ R / s²)
and to ECEF by the Jacobian of cs2cs (central differences of 1 m at the tile), its opacity
sigmoid(opacity) and its DC colour f_dc. The splat's covariance is the text's
Σ = M C Cᵀ Mᵀ (M: the upper 3×3 of its global transform, C from its SCALE and ROTATION).

Tolerances (uncompressed; SPZ in brackets, from its quantisation):
- position 1 mm [half a fixed-point step per axis, √3 · 2^-(bits+1) m, + 1 mm];
- covariance: relative Frobenius error 2·10⁻³ (the export's isotropic frame scale against the
  CRS's own Jacobian, UTM's 4·10⁻⁴, and f32); [eigenvalues each within e^(1/16) − 1 + 2·10⁻³ relative:
  log scales in 1/16 steps];
- rotation: the splat's world axes (M's rotation · R(q)) against the Gaussian's, largest
  element difference 10⁻³ [the angle between them ≤ 0.234 rad: x, y, z in 1/127.5 steps with
  w derived from them];
- opacity 10⁻⁶ [1/510 + 10⁻⁶]; DC colour 10⁻⁵ [1/(2 · 0.15 · 255) + 10⁻⁵].

`--spz-axes luf` decodes SPZ positions (and rotations) as the draft's last paragraph asks a
reader to unpack them (Left-Up-Front: x and z negated from the SPZ library's Right-Up-Back);
`stored` (default) takes them as stored, as CesiumJS 1.145 unpacks them.

Usage: khr_gs_reference.py TILESET RUN_DIR MODE CRS [--spz-axes stored|luf]
Prints one JSON object; "ok" is true when every check passed.
"""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
# The containers, not the extension: a glb's chunks, a PLY's rows, an SPZ blob's bytes.
from spz_reference import decode_spz as spz_layout  # noqa: E402
from tiles3d_reference import read_glb, read_ply, view_bytes  # noqa: E402

EXT = "KHR_gaussian_splatting"
SPZ = "KHR_gaussian_splatting_compression_spz_2"
COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5122: np.int16, 5121: np.uint8,
          5120: np.int8}
FLOAT, BYTE, UBYTE, SHORT, USHORT = 5126, 5120, 5121, 5122, 5123
# The attribute table of the text: (semantic, type, allowed (componentType, normalized)).
ALLOWED = {
    f"{EXT}:ROTATION": ("VEC4", {(FLOAT, False), (BYTE, True), (SHORT, True)}),
    f"{EXT}:SCALE": ("VEC3", {(FLOAT, False), (UBYTE, False), (UBYTE, True), (USHORT, False),
                              (USHORT, True)}),
    f"{EXT}:OPACITY": ("SCALAR", {(FLOAT, False), (UBYTE, True), (USHORT, True)}),
    f"{EXT}:SH_DEGREE_0_COEF_0": ("VEC3", {(FLOAT, False)}),
}
COEFS = {1: 3, 2: 5, 3: 7}
Y_UP_TO_Z_UP = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)


def accessor(doc, bin_, index):
    """The accessor's values as float64 (normalized integers mapped as glTF §3.11 says)."""
    a = doc["accessors"][index]
    raw = view_bytes(doc, bin_, a["bufferView"])
    n = COMPONENTS[a["type"]]
    arr = np.frombuffer(raw, dtype=DTYPES[a["componentType"]], count=a["count"] * n,
                        offset=a.get("byteOffset", 0)).reshape(a["count"], n).astype(np.float64)
    if a.get("normalized"):
        ct = a["componentType"]
        arr = {UBYTE: arr / 255.0, USHORT: arr / 65535.0,
               BYTE: np.maximum(arr / 127.0, -1.0), SHORT: np.maximum(arr / 32767.0, -1.0)}[ct]
    return arr


def tiles(tile, parent, depth=0, parent_error=None):
    """(tile, 4×4 local → ECEF, depth, parent's geometric error) of every tile."""
    m = parent @ np.array(tile.get("transform", np.eye(4).flatten(order="F").tolist()),
                          dtype=np.float64).reshape(4, 4, order="F")
    out = [(tile, m, depth, parent_error)]
    for c in tile.get("children", []):
        out += tiles(c, m, depth + 1, tile["geometricError"])
    return out


def decode_spz(blob, axes):
    """An SPZ v2 blob (spz_reference.decode_spz: the SPZ layout) as the draft maps it to the
    KHR_gaussian_splatting attributes: scales through exp; alphas, stored as bytes of the
    opacity, the library unpacks to logits and the mapping applies the sigmoid back; colours
    are the DC coefficients."""
    s = spz_layout(blob)
    rot = s["rot"] / np.linalg.norm(s["rot"], axis=1, keepdims=True)
    pos = s["pos"]
    if axes == "luf":
        # RUB → LUF: x and z negated; the rotation conjugated by diag(−1, 1, −1).
        pos = pos * np.array([-1.0, 1.0, -1.0])
        rot = rot * np.array([-1.0, 1.0, -1.0, 1.0])
    return dict(n=s["n"], deg=s["deg"], frac=s["frac"], pos=pos, alpha=s["alpha"],
                dc=s["color"], scale=np.exp(s["scale"]), rot=rot)


def quat_matrix(q):
    """Rotation matrices of unit quaternions (x, y, z, w), n×3×3 — the text's C without s."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def cs2cs(crs, pts):
    text = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in pts) + "\n"
    out = subprocess.run(["cs2cs", "-f", "%.6f", crs, "EPSG:4978"], input=text,
                         capture_output=True, text=True, check=True).stdout
    res = np.array([[float(v) for v in line.split()[:3]] for line in out.splitlines()])
    assert res.shape == (len(pts), 3)
    return res


def polar(m):
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    return r if np.linalg.det(r) > 0 else u @ np.diag([1, 1, -1]) @ vt


def check_tile(uri, tile, m, doc, bin_, axes, problems):
    """Conformance of one tile with the text; its decoded splats (tile frame) or None."""
    def bad(why):
        if len(problems) < 40:
            problems.append(f"{uri}: {why}")
    if EXT not in doc.get("extensionsUsed", []):
        bad("KHR_gaussian_splatting not in extensionsUsed")
    prim = doc["meshes"][0]["primitives"][0]
    if prim.get("mode", 4) != 0:
        bad(f"mode {prim.get('mode', 4)}, not POINTS (0)")
    ext = prim.get("extensions", {}).get(EXT)
    if ext is None:
        bad("no KHR_gaussian_splatting object on the primitive")
        return None
    if ext.get("kernel") != "ellipse":
        bad(f"kernel {ext.get('kernel')!r}")
    if ext.get("colorSpace") not in ("srgb_rec709_display", "lin_rec709_display"):
        bad(f"colorSpace {ext.get('colorSpace')!r}")
    attrs = prim["attributes"]
    accs = doc["accessors"]
    n = accs[attrs["POSITION"]]["count"] if "POSITION" in attrs else None
    if n is None or accs[attrs["POSITION"]]["type"] != "VEC3":
        bad("POSITION missing or not VEC3")
        return None
    spz = ext.get("extensions", {}).get(SPZ)
    # SPZ: the draft maps the blob to POSITION, COLOR_0, SCALE, ROTATION and SH ℓ ≥ 1.
    required = [f"{EXT}:ROTATION", f"{EXT}:SCALE"] + \
        ([] if spz else [f"{EXT}:OPACITY", f"{EXT}:SH_DEGREE_0_COEF_0"])
    for sem in required:
        if sem not in attrs:
            bad(f"{sem} missing")
            return None
    for sem, idx in attrs.items():
        a = accs[idx]
        if a["count"] != n:
            bad(f"{sem}: count {a['count']} != POSITION's {n}")
        if sem in ALLOWED:
            t, ok = ALLOWED[sem]
            if a["type"] != t or (a["componentType"], bool(a.get("normalized"))) not in ok:
                bad(f"{sem}: {a['type']} {a['componentType']} not allowed")
        if sem.startswith(f"{EXT}:SH_DEGREE_") and sem != f"{EXT}:SH_DEGREE_0_COEF_0":
            if a["type"] != "VEC3" or a["componentType"] != FLOAT:
                bad(f"{sem}: not float VEC3")
        if spz is None and "bufferView" not in a:
            bad(f"{sem}: no bufferView and no compression extension")
    degree = 0
    for l in (1, 2, 3):
        have = [f"{EXT}:SH_DEGREE_{l}_COEF_{k}" in attrs for k in range(COEFS[l])]
        if any(have) and not all(have):
            bad(f"SH degree {l} partially defined")
        if all(have):
            if degree != l - 1:
                bad(f"SH degree {l} without degree {l - 1}")
            degree = l
    if spz is not None:
        s = decode_spz(view_bytes(doc, bin_, spz["bufferView"]), axes)
        if s["n"] != n:
            bad(f"SPZ count {s['n']} != accessors' {n}")
            return None
        if s["deg"] != degree:
            bad(f"SPZ SH degree {s['deg']} != the attributes' {degree}")
        d = dict(pos=s["pos"], rot=s["rot"], scale=s["scale"], opacity=s["alpha"], dc=s["dc"],
                 frac=s["frac"])
    else:
        d = dict(pos=accessor(doc, bin_, attrs["POSITION"]),
                 rot=accessor(doc, bin_, attrs[f"{EXT}:ROTATION"]),
                 scale=accessor(doc, bin_, attrs[f"{EXT}:SCALE"]),
                 opacity=accessor(doc, bin_, attrs[f"{EXT}:OPACITY"])[:, 0],
                 dc=accessor(doc, bin_, attrs[f"{EXT}:SH_DEGREE_0_COEF_0"]))
    if np.any(d["scale"] < 0) or not np.all(np.isfinite(d["scale"])):
        bad(f"SCALE negative or not finite ({int(np.sum(d['scale'] < 0))} values < 0)")
    if np.any(d["opacity"] < 0) or np.any(d["opacity"] > 1):
        bad("OPACITY outside [0, 1]")
    norms = np.linalg.norm(d["rot"], axis=1)
    if spz is None and np.any(np.abs(norms - 1) > 1e-5):
        bad(f"ROTATION not unit quaternions (|q| {norms.min():.6f}…{norms.max():.6f})")
    # Inside the tile's box (Z-up tile frame; 3 of the largest linear scale of padding).
    box = np.array(tile["boundingVolume"]["box"], dtype=np.float64)
    c, h = box[:3], box[3:].reshape(3, 3)
    local = d["pos"] @ Y_UP_TO_Z_UP.T
    u = np.linalg.solve(h.T, (local - c).T).T
    axis_len = np.linalg.norm(h, axis=1)
    if np.any(np.abs(u) > 1 + 1e-6 + 3 * d["scale"].max(initial=0) / axis_len.min()):
        bad("a splat outside the tile's bounding box")
    return d


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    axes = "stored"
    if "--spz-axes" in sys.argv:
        axes = sys.argv[sys.argv.index("--spz-axes") + 1]
        args.remove(axes)
    tileset_dir, run, mode, crs = Path(args[0]), Path(args[1]), args[2], args[3]
    tileset = json.loads((tileset_dir / "tileset.json").read_text())
    problems, leaves, inner = [], [], 0
    max_inner, root_count = 0, None
    for tile, m, depth, parent_error in tiles(tileset["root"], np.eye(4)):
        ge = tile["geometricError"]
        if parent_error is not None and ge > parent_error:
            problems.append(f"geometricError {ge} above its parent's {parent_error}")
        if "content" not in tile:
            problems.append(f"a tile without content at depth {depth}")
            continue
        uri = tile["content"]["uri"]
        doc, bin_ = read_glb(tileset_dir / uri)
        d = check_tile(uri, tile, m, doc, bin_, axes, problems)
        if d is None:
            continue
        if depth == 0:
            root_count = len(d["pos"])
        if tile.get("children"):
            inner += 1
            max_inner = max(max_inner, len(d["pos"]))
            if ge <= 0:
                problems.append(f"{uri}: an inner tile with geometricError {ge}")
        else:
            if ge != 0:
                problems.append(f"{uri}: a leaf with geometricError {ge}")
            leaves.append((uri, m, d))

    # The run's Gaussians.
    ply = read_ply(run / mode / "semantic.ply")
    al = json.loads((run / "citymodel/alignment.json").read_text())
    ra, ta, sa = np.array(al["rotation"], np.float64), np.array(al["translation"]), al["scale"]
    origin = np.array(al["origin"], np.float64)
    pos = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
    q = np.stack([ply["rot_1"], ply["rot_2"], ply["rot_3"], ply["rot_0"]], 1).astype(np.float64)
    qn = np.linalg.norm(q, axis=1)
    logs = np.stack([ply["scale_0"], ply["scale_1"], ply["scale_2"]], 1).astype(np.float64)
    ok_rows = np.all(np.isfinite(pos), 1) & np.all(np.isfinite(logs), 1) & (qn > 0)
    idx = np.nonzero(ok_rows)[0]
    geo = origin + (pos[idx] - ta) @ ra / sa
    expected = cs2cs(crs, geo)
    tree = cKDTree(expected)
    rq = quat_matrix(q[idx] / qn[idx, None])
    sig = np.exp(logs[idx])
    opacity = 1.0 / (1.0 + np.exp(-ply["opacity"][idx].astype(np.float64)))
    dc = np.stack([ply["f_dc_0"], ply["f_dc_1"], ply["f_dc_2"]], 1)[idx].astype(np.float64)

    spz = any("frac" in d for _, _, d in leaves)
    err = {k: 0.0 for k in ["position_m", "covariance_rel", "rotation", "opacity", "color_dc"]}
    fails = {k: 0 for k in err}
    matched = np.zeros(len(idx), bool)
    total = 0
    for uri, m, d in leaves:
        n = len(d["pos"])
        total += n
        mm = m[:3, :3] @ Y_UP_TO_Z_UP
        world = d["pos"] @ mm.T + m[:3, 3]
        dist, near = tree.query(world, k=min(4, len(idx)))
        dist, near = np.atleast_2d(dist), np.atleast_2d(near)
        # The tile's Jacobian CRS → ECEF (central differences of 1 m at the tile's centroid).
        j = near[:, 0]
        c = geo[j].mean(0)
        pts = [c + e for k in range(3) for e in (np.eye(3)[k], -np.eye(3)[k])]
        ec = cs2cs(crs, np.array(pts))
        jac = np.stack([(ec[2 * k] - ec[2 * k + 1]) / 2.0 for k in range(3)], 1)
        to_crs = ra.T / sa
        a_map = jac @ to_crs
        r_map = polar(a_map)
        # The text: Σ = M C Cᵀ Mᵀ, C = R(q) diag(s).
        rt = quat_matrix(d["rot"] / np.linalg.norm(d["rot"], axis=1, keepdims=True))
        c_mat = rt * d["scale"][:, None, :]
        cov_t = np.einsum("ij,njk,nlk,ml->nim", mm, c_mat, c_mat, mm)
        r_t = np.einsum("ij,njk->nik", mm, rt)
        r_t /= np.linalg.norm(r_t, axis=1, keepdims=True)
        step = 2.0 ** -(d["frac"] + 1) * np.sqrt(3) if "frac" in d else 0.0
        tol = tolerances("frac" in d, step)
        k = near.shape[1]
        cand = []
        for kk in range(k):
            jj = near[:, kk]
            ce = np.einsum("ij,njk,nk,nlk,ml->nim", a_map, rq[jj], sig[jj] ** 2, rq[jj], a_map)
            re = np.einsum("ij,njk->nik", r_map, rq[jj])
            if "frac" in d:
                ev_t = np.linalg.eigvalsh(cov_t)
                ev_e = np.linalg.eigvalsh(ce)
                cov_err = np.max(np.abs(ev_t - ev_e) / np.maximum(ev_e, 1e-300), axis=1)
                cosang = (np.einsum("nij,nij->n", r_t, re) - 1) / 2
                rot_err = np.arccos(np.clip(cosang, -1, 1))
            else:
                cov_err = (np.linalg.norm(cov_t - ce, axis=(1, 2))
                           / np.linalg.norm(ce, axis=(1, 2)))
                rot_err = np.max(np.abs(r_t - re), axis=(1, 2))
            e = {"position_m": dist[:, kk], "covariance_rel": cov_err, "rotation": rot_err,
                 "opacity": np.abs(d["opacity"] - opacity[jj]),
                 "color_dc": np.max(np.abs(d["dc"] - dc[jj]), axis=1)}
            score = e["covariance_rel"] + e["rotation"] + e["opacity"] + e["color_dc"]
            # Only candidates as near as the nearest (within 0.1 mm) compete.
            score = np.where(dist[:, kk] <= dist[:, 0] + 1e-4, score, np.inf)
            cand.append((score, e))
        choice = np.argmin(np.stack([c[0] for c in cand], 1), axis=1)
        rows = np.arange(n)
        matched[near[rows, choice]] = True
        for key in err:
            v = np.stack([c[1][key] for c in cand], 1)[rows, choice]
            err[key] = max(err[key], float(v.max(initial=0.0)))
            fails[key] += int(np.sum(~(v <= tol[key])))
    tol = tolerances(spz, 2.0 ** -13 * np.sqrt(3))
    result = {
        "tiles": len(leaves) + inner,
        "leaves": len(leaves),
        "inner": inner,
        "root_splats": root_count,
        "max_inner_splats": max_inner,
        "splats": total,
        "expected": int(len(idx)),
        "unmatched_expected": int(np.sum(~matched)),
        "spz": spz,
        "spz_axes": axes,
        "conformance": problems,
        "max_error": err,
        "tolerance": tol,
        "fails": fails,
    }
    result["ok"] = (not problems and all(v == 0 for v in fails.values())
                    and total == len(idx) and result["unmatched_expected"] == 0)
    print(json.dumps(result))


def tolerances(spz, step):
    if spz:
        return {"position_m": step + 1e-3, "covariance_rel": np.expm1(1 / 16) + 2e-3,
                "rotation": 0.234, "opacity": 1 / 510 + 1e-6,
                "color_dc": 1 / (2 * 0.15 * 255) + 1e-5}
    return {"position_m": 1e-3, "covariance_rel": 2e-3, "rotation": 1e-3, "opacity": 1e-6,
            "color_dc": 1e-5}


if __name__ == "__main__":
    main()
