#!/usr/bin/env python3
"""Writes the COCO-RLE fixtures of the masks tests (tests/data/masks/) with pycocotools.

The masks are fixed shapes (no randomness), encoded by pycocotools.mask.encode on
Fortran-ordered uint8 arrays exactly as SAM's `coco_encode_rle` does, with SAM's derived
fields (area from the RLE, bbox as batched_mask_to_box → xywh with inclusive maxima).
Re-run after changing a fixture:  python3 scripts/make_rle_fixtures.py
"""
import json
import pathlib

import numpy as np
from pycocotools import mask as mask_utils

OUT = pathlib.Path(__file__).resolve().parent.parent / "tests" / "data" / "masks"


def sam_bbox(m):
    ys, xs = np.nonzero(m)
    if len(xs) == 0:
        return [0, 0, 0, 0]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def record(m, iou, stab, point):
    rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
    rle["counts"] = rle["counts"].decode("utf-8")
    return {
        "segmentation": {"size": [int(s) for s in rle["size"]], "counts": rle["counts"]},
        "area": int(mask_utils.area(rle)),
        "bbox": sam_bbox(m),
        "predicted_iou": iou,
        "stability_score": stab,
        "point_coords": [point],
        "crop_box": [0, 0, int(m.shape[1]), int(m.shape[0])],
    }


def shapes(h, w):
    yy, xx = np.mgrid[0:h, 0:w]
    out = []
    out.append(((yy - 12) ** 2 / 64 + (xx - 20) ** 2 / 144) <= 1)  # ellipse
    out.append((yy >= 3) & (yy < 9) & (xx >= 30) & (xx < 45))  # rectangle
    ring = ((yy - 16) ** 2 + (xx - 10) ** 2 <= 36) & ((yy - 16) ** 2 + (xx - 10) ** 2 > 9)
    out.append(ring)  # a hole: several runs per column
    out.append(np.zeros((h, w), bool))  # empty
    out.append(np.ones((h, w), bool))  # full: counts start with 0
    one = np.zeros((h, w), bool)
    one[0, 0] = True
    out.append(one)  # first pixel only
    last = np.zeros((h, w), bool)
    last[h - 1, w - 1] = True
    out.append(last)
    stripes = (xx % 7 == 0) | (yy % 5 == 2)  # many runs, large deltas
    out.append(stripes)
    return out


def rows(m):
    return ["".join("1" if v else "0" for v in r) for r in m]


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    h, w = 24, 48
    ms = shapes(h, w)
    recs = [record(m, round(0.99 - 0.03 * i, 4), round(0.98 - 0.01 * i, 4), [float(i), float(i)])
            for i, m in enumerate(ms)]
    (OUT / "sam_small.json").write_text(json.dumps(recs) + "\n")
    (OUT / "sam_small.expected.json").write_text(
        json.dumps({"size": [h, w], "masks": [rows(m) for m in ms]}, indent=1) + "\n")
    # Uncompressed RLE (counts as a list), as pycocotools' frPyObjects input.
    unc = []
    for r, m in zip(recs[:3], ms[:3]):
        flat = np.asfortranarray(m).reshape(-1, order="F").astype(np.uint8)
        counts, prev, run = [], 0, 0
        for v in flat:
            if v != prev:
                counts.append(run)
                run, prev = 0, v
            run += 1
        counts.append(run)
        back = mask_utils.decode(mask_utils.frPyObjects({"size": [h, w], "counts": counts}, h, w))
        assert (back.astype(bool) == m).all()
        u = dict(r)
        u["segmentation"] = {"size": [h, w], "counts": [int(c) for c in counts]}
        unc.append(u)
    (OUT / "sam_uncompressed.json").write_text(json.dumps(unc) + "\n")
    # Broken files: each breaks mask 2 of the good list in one way.
    bad = json.loads(json.dumps(recs))
    s = bad[2]["segmentation"]["counts"]
    # Cut right after a character with the continuation bit, so the count is unfinished.
    cut = next(i for i in range(len(s) - 1, -1, -1) if (ord(s[i]) - 48) & 0x20)
    bad[2]["segmentation"]["counts"] = s[: cut + 1]
    (OUT / "bad_truncated.json").write_text(json.dumps(bad) + "\n")
    bad = json.loads(json.dumps(recs))
    bad[2]["segmentation"]["size"] = [h, w + 1]
    (OUT / "bad_size.json").write_text(json.dumps(bad) + "\n")
    bad = json.loads(json.dumps(recs))
    bad[2]["area"] += 1
    (OUT / "bad_area.json").write_text(json.dumps(bad) + "\n")
    print(f"wrote {len(recs)} masks to {OUT}")


if __name__ == "__main__":
    main()
