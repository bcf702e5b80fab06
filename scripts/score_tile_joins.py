#!/usr/bin/env python3
"""Scores the merge's join rule for objects cut by tile borders at several fractions, against a
SIMULATED scene's truth (scoring only).

    python3 scripts/score_tile_joins.py SCENE PLAN UNTILED_RUN [--fractions 0.1,0.2,0.4] [--rule both|smaller]

SCENE:       the synth scene (reads gt/gaussians.npy: class, instance per Gaussian)
PLAN:        a plan whose tiles ran (`gs4city run-plan`; reads plan.json, merged/summary.json for
             Δ and the tiles' offsets, and per tile source.npy, run/lift/gaussians.npy,
             run/fuse/labels.json)
UNTILED_RUN: `gs4city run` of SCENE (reads lift/gaussians.npy, fuse/labels.json); `-` where the
             untiled run does not fit (its instance counts are then not printed)

The rule (docs/tile.md, "The merge"), re-implemented here with NumPy and dictionaries: groups a
of tile A and b of tile B with the same class join when the Gaussians both tiles hold that A
labels a and B labels b are at least f of each group's Gaussians that the other tile holds
(--rule smaller: of the smaller of the two only); joins closed transitively.
A join is *false* when the truth instance most of a's shared Gaussians belong to differs from
b's; a pair of same-class groups with common Gaussians and the same majority instance that is
not joined is *missed*. Instances per class (tree, person, car): labels of the class holding at
least a fifth of a simulated object of the class; printed for the tiles before the join, after
it, and for the untiled run; and the objects *split*: simulated trees, persons and cars that two or
more such labels hold a fifth of each. Independent of gs4city's code: NumPy only.
"""
import argparse
import collections
import json
import os

import numpy as np

CLASSES = ((6, "tree"), (7, "person"), (8, "car"))


def load(path):
    with open(path) as f:
        return json.load(f)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("plan")
    ap.add_argument("untiled")
    ap.add_argument("--fractions", default="0.1,0.2,0.3,0.4,0.5,0.6,0.8")
    ap.add_argument("--rule", choices=("both", "smaller"), default="both")
    a = ap.parse_args()
    truth = np.load(os.path.join(a.scene, "gt/gaussians.npy"))
    inst = truth[:, 1]
    plan = load(os.path.join(a.plan, "plan.json"))
    summary = load(os.path.join(a.plan, "merged/summary.json"))
    delta = summary["delta"]
    n = plan["gaussians"]

    # Per tile: rows (Gaussian, core, merged image id or -1); classes of the image ids.
    held = collections.defaultdict(list)
    klass = {}
    before = np.full(n, -1, dtype=np.int64)
    for t, (tp, row) in enumerate(zip(plan["tiles"], summary["tiles"])):
        d = os.path.join(a.plan, "tiles", tp["name"])
        if row["state"] != "merged":
            continue
        src = np.load(os.path.join(d, "source.npy"))
        lab = np.load(os.path.join(d, "run/lift/gaussians.npy"))[:, 0].astype(np.int64)
        table = load(os.path.join(d, "run/fuse/labels.json"))
        td = table["delta"]
        ids = np.where(lab >= td, delta + row["image_offset"] + lab - td, -1)
        for l in table["labels"]:
            if l["source"] == "image":
                klass[delta + row["image_offset"] + l["id"] - td] = l["class"]
        core = src[:, 1] == 1
        before[src[core, 0]] = ids[core]
        for i, g in zip(src[:, 0].tolist(), ids.tolist()):
            held[i].append((t, g))

    common = collections.Counter()
    tiles_of = {}
    in_shared = collections.Counter()
    shared_truth = collections.defaultdict(collections.Counter)
    for i, v in held.items():
        if len(v) < 2:
            continue
        for x in v:
            for y in v:
                if x[0] >= y[0]:
                    continue
                for (ta, ga), (tb, gb) in ((x, y), (y, x)):
                    if ga >= 0:
                        in_shared[(ga, tb)] += 1
                        shared_truth[(ga, tb)][int(inst[i])] += 1
                if x[1] >= 0 and y[1] >= 0:
                    common[(x[1], y[1])] += 1
                    tiles_of[(x[1], y[1])] = (x[0], y[0])

    def majority(g, other):
        return shared_truth[(g, other)].most_common(1)[0][0]

    objects = [o for o in np.unique(inst) if o >= 1_000_010]
    obj_class = {o: collections.Counter(truth[inst == o, 0].tolist()).most_common(1)[0][0] for o in objects}
    members = {o: np.nonzero(inst == o)[0] for o in objects}

    def instances(labels, classes):
        out = {}
        for c, name in CLASSES:
            keep = set()
            for o in objects:
                if obj_class[o] != c:
                    continue
                m = members[o]
                for l, k in collections.Counter(labels[m].tolist()).items():
                    if classes.get(l) == c and 5 * k >= len(m):
                        keep.add(l)
            out[name] = len(keep)
        return out

    def split(labels, classes):
        out = {}
        for c, name in CLASSES:
            out[name] = 0
            for o in objects:
                if obj_class[o] != c:
                    continue
                m = members[o]
                held_by = [l for l, k in collections.Counter(labels[m].tolist()).items()
                           if classes.get(l) == c and 5 * k >= len(m)]
                out[name] += len(held_by) >= 2
        return out

    truth_count = {name: sum(obj_class[o] == c for o in objects) for c, name in CLASSES}
    print(f"pairs of groups with common Gaussians: {len(common)}")
    print(f"simulated objects {truth_count}")
    if a.untiled != "-":
        rl = np.load(os.path.join(a.untiled, "lift/gaussians.npy"))[:, 0].astype(np.int64)
        rt = load(os.path.join(a.untiled, "fuse/labels.json"))
        rc = {l["id"]: l["class"] for l in rt["labels"] if l["source"] == "image"}
        print(f"instances untiled {instances(rl, rc)}; split untiled {split(rl, rc)}")
    print(f"instances tiles before the join {instances(before, klass)}; split before {split(before, klass)}")
    for f in (float(x) for x in a.fractions.split(",")):
        parent = {}

        def find(x):
            while parent.get(x, x) != x:
                x = parent[x]
            return x

        joined, false, should, missed = 0, 0, 0, 0
        missed_by_class = collections.Counter()
        for (ga, gb), k in sorted(common.items()):
            if klass[ga] != klass[gb]:
                continue
            ta, tb = tiles_of[(ga, gb)]
            sa, sb = in_shared[(ga, tb)], in_shared[(gb, ta)]
            s = max(sa, sb) if a.rule == "both" else min(sa, sb)
            same = majority(ga, tb) == majority(gb, ta)
            should += same
            if k >= f * s:
                joined += 1
                false += not same
                ra, rb = find(ga), find(gb)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
            else:
                missed += same
                if same:
                    missed_by_class[klass[ga]] += 1
        after = np.array([find(l) if l >= 0 else l for l in before.tolist()])
        print(
            f"f {f}: joins {joined}, false {false}, missed {missed} of {should}; "
            f"instances after {instances(after, klass)}; split after {split(after, klass)}; "
            f"missed by class {dict(sorted(missed_by_class.items()))}"
        )


if __name__ == "__main__":
    main()
