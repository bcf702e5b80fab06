#!/usr/bin/env python3
"""Independent NumPy reference of `gs4city eval` (no shared code), for the cross-check test.

usage: eval_reference.py --pred DIR --gt DIR --out FILE.json

Writes the same structure as gs4city's metrics.json (without "definitions"):
coarse building (ids 0..5) vs non-building over GT >= 0; fine classes
wall roof window door tree person car over GT pixels of those classes; per image then mean over
images (paper protocol) and from summed counts (dataset level). A ratio with a zero
denominator is null, except precision of a class present in GT but never predicted (0).
Predictions of another size are resized with nearest neighbour at pixel centres.
"""
import argparse
import json
import os
import sys

import numpy as np

SUFFIX = ".class.npy"
NAMES = ["wall", "roof", "window", "door", "ground_surface", "installation", "tree",
         "person", "car", "road", "water", "other"]
FINE_IDS = [0, 1, 2, 3, 6, 7, 8]
FINE = [NAMES[i] for i in FINE_IDS]
NF = len(FINE_IDS)


def stems(d):
    return {f[:-len(SUFFIX)]: os.path.join(d, f) for f in os.listdir(d)
            if f.endswith(SUFFIX) and len(f) > len(SUFFIX)}


def load(path):
    a = np.load(path, allow_pickle=False)
    if a.dtype != np.int32 or a.ndim != 2 or a.size == 0:
        sys.exit(f"{path}: bad class map {a.dtype} {a.shape}")
    return a


def resize(pred, shape):
    h, w = pred.shape
    H, W = shape
    rows = np.minimum((2 * np.arange(H) + 1) * h // (2 * H), h - 1)
    cols = np.minimum((2 * np.arange(W) + 1) * w // (2 * W), w - 1)
    return pred[rows[:, None], cols[None, :]]


def div(a, b):
    return None if b == 0 else float(a) / float(b)


def prec(tp, fp, fn):
    if tp + fp == 0:
        return 0.0 if tp + fn > 0 else None
    return float(tp) / float(tp + fp)


def coarse_block(tp, fp, fn, tn):
    tp, fp, fn, tn = int(tp), int(fp), int(fn), int(tn)
    return {"tp": tp, "fp": fp, "fn": fn, "tn": tn,
            "iou": div(tp, tp + fp + fn), "accuracy": div(tp + tn, tp + fp + fn + tn),
            "precision": prec(tp, fp, fn), "recall": div(tp, tp + fn),
            "f1": div(2 * tp, 2 * tp + fp + fn)}


def fine_block(conf):
    """conf: NF x (NF+1) int array (rows GT fine class, columns predicted fine class | other)."""
    gt = conf.sum(axis=1)
    pred = conf[:, :NF].sum(axis=0)
    tp = np.diag(conf[:, :NF])
    out = {"pixels": int(conf.sum()), "classes_present": [], "iou": {}, "precision": {},
           "recall": {}, "gt_pixels": {}, "pred_pixels": {}, "tp": {},
           "confusion": conf.astype(int).tolist()}
    ious = []
    for k, name in enumerate(FINE):
        t, g, p = int(tp[k]), int(gt[k]), int(pred[k])
        fp, fn = p - t, g - t
        out["gt_pixels"][name], out["pred_pixels"][name], out["tp"][name] = g, p, t
        if g == 0:
            out["iou"][name] = out["precision"][name] = out["recall"][name] = None
            continue
        out["classes_present"].append(name)
        iou = t / (t + fp + fn)
        ious.append(iou)
        out["iou"][name] = iou
        out["precision"][name] = prec(t, fp, fn)
        out["recall"][name] = t / g
    out["miou"] = float(np.mean(ious)) if ious else None
    return out


def counts(gt, pred):
    valid = gt >= 0
    g, p = gt[valid], pred[valid]
    gb = (g >= 0) & (g <= 5)
    pb = (p >= 0) & (p <= 5)
    coarse = (np.sum(gb & pb), np.sum(~gb & pb), np.sum(gb & ~pb), np.sum(~gb & ~pb))
    # fine: map ids to 0..NF-1, everything else to NF
    lut = np.full(12, NF, dtype=np.int64)
    lut[FINE_IDS] = np.arange(NF)
    gi = lut[g]
    keep = gi < NF
    pv = p[keep]
    pi = np.where((pv >= 0) & (pv <= 11), lut[np.clip(pv, 0, 11)], NF)
    conf = np.bincount(gi[keep] * (NF + 1) + pi, minlength=NF * (NF + 1)).reshape(NF, NF + 1)
    return int(valid.sum()), int((~valid).sum()), coarse, conf


def mean(values):
    xs = [v for v in values if v is not None]
    return {"mean": (sum(xs) / len(xs)) if xs else None, "images": len(xs)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pred", required=True)
    ap.add_argument("--gt", required=True)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    gts, preds = stems(a.gt), stems(a.pred)
    rows = []
    tot_valid = tot_ign = 0
    tot_coarse = np.zeros(4, dtype=np.int64)
    tot_conf = np.zeros((NF, NF + 1), dtype=np.int64)
    for stem in sorted(gts):
        if stem not in preds:
            sys.exit(f"missing prediction {stem}")
        gt = load(gts[stem])
        pred = load(preds[stem])
        psize = list(pred.shape)
        if pred.shape != gt.shape:
            pred = resize(pred, gt.shape)
        valid, ign, coarse, conf = counts(gt, pred)
        tot_valid += valid
        tot_ign += ign
        tot_coarse += np.array(coarse, dtype=np.int64)
        tot_conf += conf
        rows.append({
            "stem": stem, "gt_size": list(gt.shape), "pred_size": psize,
            "resized": psize != list(gt.shape), "valid_pixels": valid, "ignored_pixels": ign,
            "unknown_pred_values": int(np.sum((pred < -1) | (pred > 11))),
            "coarse": coarse_block(*coarse) if valid > 0 else None,
            "fine": fine_block(conf) if conf.sum() > 0 else None,
        })
    cr = [r["coarse"] for r in rows if r["coarse"] is not None]
    fr = [r["fine"] for r in rows if r["fine"] is not None]
    paper = {
        "images_coarse": len(cr), "images_fine": len(fr),
        "coarse_skipped_no_valid_gt": len(rows) - len(cr),
        "fine_skipped_no_fine_gt": len(rows) - len(fr),
        "coarse": {k: mean(r[k] for r in cr)
                   for k in ["iou", "accuracy", "precision", "recall", "f1"]},
        "miou": mean(r["miou"] for r in fr),
    }
    for m in ["iou", "precision", "recall"]:
        paper[m] = {n: mean(r[m][n] for r in fr) for n in FINE}
    out = {
        "fine_classes": FINE, "confusion_columns": FINE + ["other"], "images": len(rows),
        "predictions_without_gt": sorted(s for s in preds if s not in gts),
        "resized_predictions": sum(r["resized"] for r in rows),
        "paper": paper,
        "dataset": {"valid_pixels": tot_valid, "ignored_pixels": tot_ign,
                    "coarse": coarse_block(*tot_coarse), "fine": fine_block(tot_conf)},
        "per_image": rows,
    }
    with open(a.out, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
