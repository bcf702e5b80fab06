#!/usr/bin/env python3
"""Where a class's training supervision goes wrong: the fused label maps of a finished run
(`R/fuse/<stem>.ids.npy` + `R/fuse/labels.json`) against a SIMULATED scene's truth
(`S/gt/<stem>.class.npy`), over every view the fuse stage wrote (the training views).

Scoring only (it reads `gt/`; no stage does). Usage:

    python3 scripts/supervision_errors.py R S [--class 3] [--band 2]

Prints, for the class (default 3 = door): true positives, false positives, false negatives,
precision and IoU; the false positives within `--band` pixels of a true pixel of the class (the
outline) and farther; and the truth classes of the false positives. numpy only.
"""
import argparse
import glob
import json
import os

import numpy as np


def dilate(mask, r):
    """Square dilation by r pixels (the 8-neighbourhood, r times), numpy shifts only."""
    out = mask.copy()
    for _ in range(r):
        m = out.copy()
        m[1:, :] |= out[:-1, :]
        m[:-1, :] |= out[1:, :]
        m[:, 1:] |= out[:, :-1]
        m[:, :-1] |= out[:, 1:]
        m[1:, 1:] |= out[:-1, :-1]
        m[1:, :-1] |= out[:-1, 1:]
        m[:-1, 1:] |= out[1:, :-1]
        m[:-1, :-1] |= out[1:, 1:]
        out = m
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("scene")
    ap.add_argument("--class", dest="cls", type=int, default=3)
    ap.add_argument("--band", type=int, default=2)
    a = ap.parse_args()
    labels = json.load(open(os.path.join(a.run, "fuse", "labels.json")))["labels"]
    lut = np.full(max(l["id"] for l in labels) + 2, -1, np.int64)
    for l in labels:
        lut[l["id"]] = l["class"]
    tp = fp = fn = near = 0
    by_truth = {}
    views = sorted(glob.glob(os.path.join(a.run, "fuse", "*.ids.npy")))
    for f in views:
        stem = os.path.basename(f)[: -len(".ids.npy")]
        ids = np.load(f)
        gt = np.load(os.path.join(a.scene, "gt", stem + ".class.npy"))
        pred = np.where(ids >= 0, lut[np.clip(ids, 0, len(lut) - 1)], -1)
        t, p = gt == a.cls, pred == a.cls
        wrong = p & ~t
        tp += int((t & p).sum())
        fp += int(wrong.sum())
        fn += int((t & ~p).sum())
        near += int((wrong & dilate(t, a.band)).sum())
        for c, n in zip(*np.unique(gt[wrong], return_counts=True)):
            by_truth[int(c)] = by_truth.get(int(c), 0) + int(n)
    print(f"{len(views)} views, class {a.cls}: tp {tp}, fp {fp}, fn {fn}, "
          f"precision {tp / max(tp + fp, 1):.4f}, IoU {tp / max(tp + fp + fn, 1):.4f}")
    print(f"false positives within {a.band} px of the class's truth: {near}; farther: {fp - near}")
    print("false positives by truth class:", dict(sorted(by_truth.items(), key=lambda x: -x[1])))


if __name__ == "__main__":
    main()
