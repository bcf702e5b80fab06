#!/usr/bin/env python3
"""Scores a run's completeness report against a SIMULATED scene's model edit (scoring only).

    python3 scripts/score_completeness.py RUN SCENE FULL_CITYMODEL [--min-iou 0.3] [--m-view 3]

RUN:            a `gs4city run` folder (reads openings/completeness.json, citymodel/alignment.json)
SCENE:          the synth scene made with --drop-openings (reads gt/model_edit.json: the dropped
                opening ids, and gt/<stem>.hier.npy: which openings the training views see)
FULL_CITYMODEL: a `gs4city citymodel` output of the *complete* model in the same frame
                (mesh.ply + semantics.json), e.g. R/citymodel of a run on the complete scene.

A finding ("missing in model") matches a dropped opening of the same building that lies on the
finding's wall plane (mean distance of its mesh vertices <= --plane-tol metres x scale; the
truth's parent wall is often a small reveal surface, not the facade) when their rectangles on
that plane (the finding's own corners; the dropped opening's vertices projected, bounding box)
have IoU >= --min-iou; one-to-one, best IoU first.
Classes: matched pairs counted as "<truth class> as <finding class>".
Precision = matched findings / findings; recall = matched dropped / dropped, over all dropped
openings and over those seen (>= 1e-4 of the image) in >= --m-view training views of the GT.
Independent of gs4city's code: NumPy only.
"""
import argparse
import json
import os
import sys

import numpy as np


def read_mesh(path):
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    nv = int(header.split("element vertex ")[1].split()[0])
    nf = int(header.split("element face ")[1].split()[0])
    v = np.frombuffer(data, dtype="<f4", count=3 * nv, offset=end).reshape(nv, 3).astype(np.float64)
    fdt = np.dtype([("n", "u1"), ("i", "<i4", 3), ("feature", "<i4"), ("surface", "<i4"), ("part", "<i4")])
    f = np.frombuffer(data, dtype=fdt, count=nf, offset=end + 12 * nv)
    assert (f["n"] == 3).all()
    return v, f


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("scene")
    ap.add_argument("full")
    ap.add_argument("--min-iou", type=float, default=0.3)
    ap.add_argument("--m-view", type=int, default=3)
    ap.add_argument("--plane-tol", type=float, default=0.5)
    ap.add_argument("--test-every", type=int, default=8)
    a = ap.parse_args()

    edit = json.load(open(os.path.join(a.scene, "gt", "model_edit.json")))
    dropped = {d["object_id"]: d for d in edit["dropped"]}
    ents = json.load(open(os.path.join(a.full, "semantics.json")))["entities"]
    by_oid = {e["object_id"]: e for e in ents}
    # Every entity's dropped root (itself or an ancestor that was dropped).
    root_of = {}
    for e in ents:
        x = e
        while x is not None:
            if x["object_id"] in dropped:
                root_of[e["id"]] = x["object_id"]
                break
            x = ents[x["parent"]] if x["parent"] is not None else None
    v, f = read_mesh(os.path.join(a.full, "mesh.ply"))
    pts = {oid: [] for oid in dropped}
    for fi in np.nonzero(f["part"] >= 0)[0]:
        r = root_of.get(int(f["part"][fi]))
        if r is not None:
            pts[r].extend(f["i"][fi].tolist())
    al = json.load(open(os.path.join(a.run, "citymodel", "alignment.json")))
    R = np.array(al["rotation"], dtype=np.float64).reshape(3, 3)
    s, t, o = al["scale"], np.array(al["translation"]), np.array(al["origin"])

    def to_scene(p):
        return s * (R @ (np.asarray(p, dtype=np.float64) - o)) + t

    comp = json.load(open(os.path.join(a.run, "openings", "completeness.json")))
    found = comp["missing_in_model"]
    pairs = []
    for fi, fd in enumerate(found):
        c = [to_scene(p) for p in fd["polygon"]]
        p0 = c[0]
        du, dv = c[1] - c[0], c[3] - c[0]
        lu, lv = np.linalg.norm(du), np.linalg.norm(dv)
        u, w = du / lu, dv / lv
        n = np.cross(u, w)
        rf = (0.0, 0.0, lu, lv)
        for oid, d in dropped.items():
            if d["building"] != fd["building_object_id"] or not pts[oid]:
                continue
            q = v[np.array(pts[oid])] - p0
            if np.abs(q @ n).mean() > a.plane_tol * s:
                continue
            qu, qv = q @ u, q @ w
            rd = (qu.min(), qv.min(), qu.max(), qv.max())
            iw = min(rf[2], rd[2]) - max(rf[0], rd[0])
            ih = min(rf[3], rd[3]) - max(rf[1], rd[1])
            inter = max(iw, 0) * max(ih, 0)
            union = (rf[2] - rf[0]) * (rf[3] - rf[1]) + (rd[2] - rd[0]) * (rd[3] - rd[1]) - inter
            iou = inter / union if union > 0 else 0.0
            if iou >= a.min_iou:
                pairs.append((iou, fi, oid))
    pairs.sort(reverse=True)
    used_f, used_d = set(), set()
    classes = {}
    for iou, fi, oid in pairs:
        if fi in used_f or oid in used_d:
            continue
        used_f.add(fi)
        used_d.add(oid)
        key = "%s as %s" % (dropped[oid]["class"], found[fi]["class"])
        classes[key] = classes.get(key, 0) + 1
    # Dropped openings the training views see (GT part channel, full-model entity ids).
    gt = os.path.join(a.scene, "gt")
    stems = sorted(n[: -len(".hier.npy")] for n in os.listdir(gt) if n.endswith(".hier.npy"))
    train = [st for i, st in enumerate(stems) if a.test_every == 0 or i % a.test_every != 0]
    views = {oid: 0 for oid in dropped}
    for st in train:
        h = np.load(os.path.join(gt, st + ".hier.npy"))
        part = h[2]
        ids, counts = np.unique(part[part >= 0], return_counts=True)
        minpx = 1e-4 * part.size
        here = set()
        for i, c in zip(ids.tolist(), counts.tolist()):
            r = root_of.get(i)
            if r is not None and c >= minpx:
                here.add(r)
        for r in here:
            views[r] += 1
    seen = {oid for oid, n in views.items() if n >= a.m_view}
    out = {
        "SIMULATED": True,
        "findings": len(found),
        "dropped": len(dropped),
        "dropped_seen": len(seen),
        "matched": len(used_f),
        "precision": len(used_f) / len(found) if found else None,
        "recall": len(used_d) / len(dropped) if dropped else None,
        "recall_seen": len(used_d & seen) / len(seen) if seen else None,
        "min_iou": a.min_iou,
        "classes": dict(sorted(classes.items())),
    }
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
