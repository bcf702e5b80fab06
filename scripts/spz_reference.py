#!/usr/bin/env python3
"""SPZ v2 cross-check of `gs4city export --format 3dtiles --spz` (tests/export_3dtiles.rs).

Usage: spz_reference.py PLAIN_TILESET SPZ_TILESET

Both tilesets are exports of the same run with the same options, one uncompressed, one with
--spz (the same quadtree, the same tiles, the splats in the same order). Every SPZ blob is
decoded here, written from the SPZ v2 layout (Niantic's spz format: gzip of a 16-byte header
"NGSP", version 2, count, SH degree, fractional bits, flags, reserved; then 24-bit fixed-point
positions, alphas, DC colours (scale 0.15), log scales (+10, ×16), quaternion x y z (w ≥ 0
derived), SH bytes (x·128 + 128)), and compared with the uncompressed tile's attributes after
clamping them to the range the bytes can hold. Prints one JSON object: per field the largest
error and the quantisation step it is held to, the glTF structure checks and the counts.
"""
import gzip
import json
import struct
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tiles3d_reference import accessor, read_glb, view_bytes  # noqa: E402

EXT = "KHR_gaussian_splatting_compression_spz_2"


def decode_spz(blob):
    raw = gzip.decompress(blob)
    magic, version, n, deg, frac, flags, _ = struct.unpack_from("<IIIBBBB", raw, 0)
    assert magic == 0x5053474E, hex(magic)
    assert version == 2, version
    o = 16
    b = np.frombuffer(raw, dtype=np.uint8, count=n * 9, offset=o).reshape(n, 3, 3).astype(np.int32)
    fixed = b[:, :, 0] | (b[:, :, 1] << 8) | (b[:, :, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    pos = fixed / float(1 << frac)
    o += n * 9
    alpha = np.frombuffer(raw, np.uint8, n, o) / 255.0
    o += n
    color = (np.frombuffer(raw, np.uint8, n * 3, o).reshape(n, 3) / 255.0 - 0.5) / 0.15
    o += n * 3
    scale = np.frombuffer(raw, np.uint8, n * 3, o).reshape(n, 3) / 16.0 - 10.0
    o += n * 3
    xyz = np.frombuffer(raw, np.uint8, n * 3, o).reshape(n, 3) / 127.5 - 1.0
    o += n * 3
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz ** 2).sum(1)))
    rot = np.concatenate([xyz, w[:, None]], 1)
    dim = (deg + 1) ** 2 - 1
    sh = (np.frombuffer(raw, np.uint8, n * dim * 3, o).reshape(n, dim, 3) - 128.0) / 128.0
    o += n * dim * 3
    assert o == len(raw), (o, len(raw))
    return dict(n=n, deg=deg, frac=frac, flags=flags, pos=pos, alpha=alpha, color=color,
                scale=scale, rot=rot, sh=sh)


def main():
    plain_dir, spz_dir = Path(sys.argv[1]), Path(sys.argv[2])
    err = {k: 0.0 for k in ["position_m", "alpha", "color_dc", "log_scale", "rotation_xyz",
                            "rotation_angle_rad", "sh1", "sh_rest"]}
    out = {"tiles": 0, "splats": 0, "structure_errors": []}
    for p in sorted((plain_dir / "tiles").glob("*.glb")):
        q = spz_dir / "tiles" / p.name
        d0, b0 = read_glb(p)
        d1, b1 = read_glb(q)
        prim0 = d0["meshes"][0]["primitives"][0]
        prim1 = d1["meshes"][0]["primitives"][0]
        ext = prim1["extensions"]["KHR_gaussian_splatting"]["extensions"][EXT]
        s = decode_spz(view_bytes(d1, b1, ext["bufferView"]))
        a0 = {k: accessor(d0, b0, v) for k, v in prim0["attributes"].items()}
        n = s["n"]
        out["tiles"] += 1
        out["splats"] += n
        if EXT not in d1.get("extensionsUsed", []):
            out["structure_errors"].append(f"{q.name}: {EXT} not in extensionsUsed")
        for k, v in prim1["attributes"].items():
            acc = d1["accessors"][v]
            if acc["count"] != n:
                out["structure_errors"].append(f"{q.name}: {k} count {acc['count']} != {n}")
            spz_attr = not k.startswith("_FEATURE_ID_")
            if spz_attr == ("bufferView" in acc):
                out["structure_errors"].append(f"{q.name}: {k} bufferView presence wrong")
            if k.startswith("_FEATURE_ID_") and not np.array_equal(accessor(d1, b1, v), a0[k]):
                out["structure_errors"].append(f"{q.name}: {k} differs from the plain export")
        m0 = d0.get("extensions", {}).get("EXT_structural_metadata", {})
        m1 = d1.get("extensions", {}).get("EXT_structural_metadata", {})
        same = m0.get("schema") == m1.get("schema") and len(m0.get("propertyTables", [])) == len(
            m1.get("propertyTables", []))
        for t0, t1 in zip(m0.get("propertyTables", []), m1.get("propertyTables", [])):
            same &= (t0["class"], t0["count"], sorted(t0["properties"])) == (
                t1["class"], t1["count"], sorted(t1["properties"]))
            for k, v0 in t0["properties"].items():
                v1 = t1["properties"].get(k, {})
                for part in ["values", "stringOffsets"]:
                    if part in v0:
                        same &= part in v1 and view_bytes(d0, b0, v0[part]) == view_bytes(d1, b1, v1[part])
        if not same:
            out["structure_errors"].append(f"{q.name}: property tables differ")
        if prim1["extensions"].get("EXT_mesh_features") != prim0["extensions"].get("EXT_mesh_features"):
            out["structure_errors"].append(f"{q.name}: EXT_mesh_features differs")
        pos = a0["POSITION"].astype(np.float64)
        lim = (1 << 23) / float(1 << s["frac"])
        # Relative to the tile's half step (its fractional bits: 12, fewer for a large tile).
        err["position_m"] = max(err["position_m"],
                                float(np.abs(s["pos"] - pos).max()) * 2.0 ** (s["frac"] - 12))
        assert np.abs(pos).max() < lim
        op = a0["KHR_gaussian_splatting:OPACITY"][:, 0].astype(np.float64)
        err["alpha"] = max(err["alpha"], float(np.abs(s["alpha"] - op).max()))
        dc = a0["KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"].astype(np.float64)
        dc = np.clip(dc, -0.5 / 0.15, 0.5 / 0.15)
        err["color_dc"] = max(err["color_dc"], float(np.abs(s["color"] - dc).max()))
        # The uncompressed SCALE is linear, SPZ holds log scales.
        sc = np.clip(np.log(a0["KHR_gaussian_splatting:SCALE"].astype(np.float64)), -10.0,
                     255 / 16 - 10)
        err["log_scale"] = max(err["log_scale"], float(np.abs(s["scale"] - sc).max()))
        r = a0["KHR_gaussian_splatting:ROTATION"].astype(np.float64)
        r = r / np.linalg.norm(r, axis=1, keepdims=True)
        r = np.where(r[:, 3:4] < 0, -r, r)
        err["rotation_xyz"] = max(err["rotation_xyz"], float(np.abs(s["rot"][:, :3] - r[:, :3]).max()))
        dot = np.clip(np.abs((s["rot"] / np.linalg.norm(s["rot"], axis=1, keepdims=True) * r).sum(1)), 0, 1)
        err["rotation_angle_rad"] = max(err["rotation_angle_rad"], float((2 * np.arccos(dot)).max()))
        deg = s["deg"]
        for l in range(1, deg + 1):
            for m in range(2 * l + 1):
                j = l * l - 1 + m
                ref = np.clip(a0[f"KHR_gaussian_splatting:SH_DEGREE_{l}_COEF_{m}"].astype(np.float64),
                              -1.0, 127 / 128)
                key = "sh1" if l == 1 else "sh_rest"
                err[key] = max(err[key], float(np.abs(s["sh"][:, j, :] - ref).max()))
        out["sh_degree"] = deg
    out["max_error"] = err
    # The steps: half a quantisation step (and f32 rounding of the reference).
    out["half_step"] = {
        # position_m: in units of a 12-bit tile's step.
        "position_m": 0.5 / 4096 + 1e-6, "alpha": 0.5 / 255 + 1e-6,
        "color_dc": 0.5 / (0.15 * 255) + 1e-6, "log_scale": 0.5 / 16 + 1e-6,
        "rotation_xyz": 0.5 / 127.5 + 1e-6,
        # w = sqrt(1 - |xyz|²) from xyz each off by d: |Δw| <= sqrt(2·sqrt(3)·d + 3d²), the
        # angle 2·|Δq|.
        "rotation_angle_rad": 2 * np.sqrt(2 * np.sqrt(3) * (0.5 / 127.5) + 3 * (0.5 / 127.5) ** 2) + 1e-3,
        "sh1": 4.5 / 128 + 1e-6, "sh_rest": 8.5 / 128 + 1e-6,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
