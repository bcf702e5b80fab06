#!/usr/bin/env python3
"""Cross-check of gs4city's COCO RLE against pycocotools (driven by tests/masks.rs).

    python3 scripts/rle_crosscheck.py DIR

1. Reads DIR/rust.json (SAM masks encoded by gs4city) and DIR/rust_masks.npy (uint8 N×H×W,
   the same masks as pixels): decodes every RLE with pycocotools and compares pixels, area,
   and re-encodes the pixels to compare the compressed string byte for byte.
2. Writes DIR/py.json (seeded random masks encoded by pycocotools, SAM fields) and
   DIR/py_masks.npy for gs4city to decode.
Prints "OK <n checked> <n written>" and exits 0, or prints the first mismatch and exits 1.
"""
import json
import pathlib
import sys

import numpy as np
from pycocotools import mask as mask_utils


def fail(msg):
    print("MISMATCH", msg)
    sys.exit(1)


def sam_bbox(m):
    ys, xs = np.nonzero(m)
    if len(xs) == 0:
        return [0, 0, 0, 0]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def main():
    d = pathlib.Path(sys.argv[1])
    recs = json.loads((d / "rust.json").read_text())
    masks = np.load(d / "rust_masks.npy")
    if len(recs) != len(masks):
        fail(f"{len(recs)} records vs {len(masks)} masks")
    for i, (r, m) in enumerate(zip(recs, masks)):
        seg = dict(r["segmentation"])
        h, w = seg["size"]
        if m.shape != (h, w):
            fail(f"mask {i}: size {seg['size']} vs {m.shape}")
        dec = mask_utils.decode({"size": [h, w], "counts": seg["counts"].encode()})
        if not (dec == m).all():
            fail(f"mask {i}: pycocotools decodes other pixels")
        if int(mask_utils.area({"size": [h, w], "counts": seg["counts"].encode()})) != r["area"]:
            fail(f"mask {i}: area")
        enc = mask_utils.encode(np.asfortranarray(m))["counts"].decode()
        if enc != seg["counts"]:
            fail(f"mask {i}: pycocotools encodes {enc!r}, gs4city wrote {seg['counts']!r}")
    rng = np.random.default_rng(12345)
    out, pix = [], []
    h, w = 37, 53
    for k in range(60):
        kind = k % 6
        if kind == 0:
            m = rng.random((h, w)) < rng.random()
        elif kind == 1:
            m = np.zeros((h, w), bool)
        elif kind == 2:
            m = np.ones((h, w), bool)
        elif kind == 3:
            m = np.zeros((h, w), bool)
            m[rng.integers(h), rng.integers(w)] = True
        elif kind == 4:
            yy, xx = np.mgrid[0:h, 0:w]
            m = (yy - rng.integers(h)) ** 2 + (xx - rng.integers(w)) ** 2 < rng.integers(1, 600)
        else:
            m = np.zeros((h, w), bool)
            m[:, rng.integers(w)] = True
            m[rng.integers(h), :] = True
        m = m.astype(np.uint8)
        rle = mask_utils.encode(np.asfortranarray(m))
        out.append({
            "segmentation": {"size": [h, w], "counts": rle["counts"].decode()},
            "area": int(mask_utils.area(rle)),
            "bbox": sam_bbox(m),
            "predicted_iou": 0.9,
            "stability_score": 0.95,
            "point_coords": [[0.0, 0.0]],
            "crop_box": [0, 0, w, h],
        })
        pix.append(m)
    (d / "py.json").write_text(json.dumps(out))
    np.save(d / "py_masks.npy", np.stack(pix))
    print("OK", len(recs), len(out))


if __name__ == "__main__":
    main()
