#!/usr/bin/env python3
"""Where a plan's tile CPU goes: per tile its views, Gaussians (core + margin, core), CPU s
(status.json) and stage seconds (run/summary.json), the totals per stage, and a least-squares fit
of CPU s = a·views + b·(million Gaussians) + c over the tiles (BENCHMARKS.md, "Tiles").

    python3 scripts/tile_profile.py PLAN_OR_COPY [PLAN_OR_COPY…]

PLAN_OR_COPY: a plan folder whose tiles ran (plan.json, tiles/<t>/status.json,
tiles/<t>/run/summary.json) or a folder holding plan.json and <t>.status.json, <t>.summary.json
copied from one. Needs numpy.
"""
import json
import os
import sys

import numpy as np


def tile_files(d, name):
    a = os.path.join(d, "tiles", name)
    if os.path.isdir(a):
        return os.path.join(a, "status.json"), os.path.join(a, "run/summary.json")
    return os.path.join(d, f"{name}.status.json"), os.path.join(d, f"{name}.summary.json")


for d in sys.argv[1:]:
    plan = json.load(open(os.path.join(d, "plan.json")))
    rows, stages = [], {}
    for t in plan["tiles"]:
        st, su = tile_files(d, t["name"])
        if not (t["runnable"] and os.path.exists(st) and os.path.exists(su)):
            continue
        s = json.load(open(st))
        secs = {x["stage"]: x["seconds"] for x in json.load(open(su))["stages"]}
        for k, v in secs.items():
            stages[k] = stages.get(k, 0.0) + v
        rows.append((t["name"], t["views"], t["gaussians"], t["core_gaussians"], s["cpu_seconds"], s["seconds"]))
    print(f"{d}: {len(rows)} tiles of {sum(t['runnable'] for t in plan['tiles'])} runnable")
    print("tile\tviews\tgaussians\tcore\tcpu_s\twall_s")
    for r in rows:
        print("\t".join(str(x) for x in r))
    v = np.array([r[1] for r in rows], float)
    g = np.array([r[2] for r in rows], float) / 1e6
    c = np.array([r[4] for r in rows], float)
    print(f"views {v.sum():.0f}, CPU s {c.sum():.1f}, CPU s per view joined {c.sum() / v.sum():.3f}")
    wall = sum(stages.values())
    print("stage seconds (wall, summed over tiles): " + ", ".join(
        f"{k} {x:.0f} ({100 * x / wall:.0f} %)" for k, x in sorted(stages.items(), key=lambda kv: -kv[1])))
    if len(rows) >= 4:
        A = np.stack([v, g, np.ones_like(v)], 1)
        coef, *_ = np.linalg.lstsq(A, c, rcond=None)
        pred = A @ coef
        r2 = 1 - ((c - pred) ** 2).sum() / ((c - c.mean()) ** 2).sum()
        print(f"fit: CPU s = {coef[0]:.3f}·views + {coef[1]:.2f}·MGaussians + {coef[2]:.2f} (R² {r2:.3f})")
