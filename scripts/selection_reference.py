#!/usr/bin/env python3
"""Independent reading of `gs4city query` selections, from docs/query.md and a run's files only.

Shares no code with gs4city. A selection picks labels of the run's label table and with them
every Gaussian carrying one of those labels. This script evaluates a selection expression over

  R/<mode>/semantic.ply       per Gaussian its label (read with the pip package plyfile)
  R/citymodel/semantics.json  the city entities: class, level, parent, gml:id, attributes
  R/fuse/labels.json          the label table (without R/fuse: one label per entity)
  R/fuse/label_features.npy   per-label features, and S/features/prompts.json (text terms)

with the documented rules: `class=X` selects entities of class X or below one (Window =
WindowSurface, Door = DoorSurface, Opening, BoundarySurface; prefixes and case ignored; image
labels have no class), `level=`, `id=G` (that entity alone), `within(G)` (G and its
descendants), `category=C` (labels whose evaluation class is C, city or image), `label=N`,
`text("P")` for a prompt P (relevancy min_j sigmoid(T (f.q - f.n_j)) >= tau with T = 10,
tau = 0.85, the negatives every other prompt whose cosine with q is below 0.8), attribute
comparisons with inheritance from the nearest ancestor that has the attribute (numbers as
numbers, a missing attribute satisfies nothing, a list matches when one element does); `not`,
`and`, `or`, parentheses. Free text, units after numbers and `attr("...")` are not read here
(exit 2 naming the term).

Usage: python3 scripts/selection_reference.py RUN EXPR [EXPR ...] [--mode lift|train] [--indices]
Prints {expr: {"labels": [...], "gaussians": N[, "indices": [...]]}} as JSON.
"""
import argparse
import json
import math
import os
import re
import sys

import numpy as np
from plyfile import PlyData

NAMES = ["wall", "roof", "window", "door", "ground_surface", "installation", "tree", "person",
         "car", "road", "water", "other"]
SAME = {"windowsurface": "window", "doorsurface": "door"}
ABSTRACT = {"opening": {"window", "door"},
            "boundarysurface": {"wallsurface", "roofsurface", "groundsurface", "closuresurface",
                                "outerceilingsurface", "outerfloorsurface"}}
TOKEN = re.compile(r"\s*(?:(?P<num>-?\d+(?:\.\d+)?(?![\w.]))|(?P<str>\"[^\"]*\"|'[^']*')|"
                   r"(?P<op><=|>=|!=|=|<|>)|(?P<par>[()])|(?P<word>[A-Za-z0-9_.:@#/+-]+))")


def unsupported(what):
    print(f"selection_reference: {what} is not read here", file=sys.stderr)
    sys.exit(2)


def tokens(expr):
    out, i = [], 0
    while i < len(expr):
        if expr[i:].strip() == "":
            break
        m = TOKEN.match(expr, i)
        if not m:
            unsupported(f"`{expr[i:]}`")
        kind = m.lastgroup
        text = m.group(kind)
        if kind == "str":
            text = text[1:-1]
        out.append((kind, text))
        i = m.end()
    return out


class Parser:
    """expr := and ("or" and)*; and := unary ("and" unary)*; unary := "not" unary | "(" expr ")" |
    term. Returns a predicate over labels (a function label -> bool)."""

    def __init__(self, toks, world):
        self.t, self.i, self.w = toks, 0, world

    def peek(self, k=0):
        return self.t[self.i + k] if self.i + k < len(self.t) else (None, None)

    def kw(self, word):
        kind, text = self.peek()
        if kind == "word" and text.lower() == word:
            self.i += 1
            return True
        return False

    def take(self):
        tok = self.peek()
        self.i += 1
        return tok

    def expr(self):
        terms = [self.conj()]
        while self.kw("or"):
            terms.append(self.conj())
        return lambda l: any(f(l) for f in terms)

    def conj(self):
        terms = [self.unary()]
        while self.kw("and"):
            terms.append(self.unary())
        return lambda l: all(f(l) for f in terms)

    def unary(self):
        if self.kw("not"):
            f = self.unary()
            return lambda l: not f(l)
        if self.peek() == ("par", "("):
            self.take()
            f = self.expr()
            if self.take() != ("par", ")"):
                unsupported("an unbalanced parenthesis")
            return f
        return self.term()

    def term(self):
        kind, name = self.take()
        if kind != "word":
            unsupported(f"`{name}`")
        key = name.lower()
        if key in ("within", "text", "attr") and self.peek() == ("par", "("):
            self.take()
            _, value = self.take()
            if self.take() != ("par", ")"):
                unsupported(f"`{name}(`")
            if key == "within":
                return self.w.within(value)
            if key == "text":
                return self.w.text(value)
            unsupported("attr(...)")
        _, op = self.take()
        vkind, value = self.take()
        if self.peek()[0] == "word" and self.peek()[1].lower() not in ("and", "or") \
                and vkind == "num":
            unsupported(f"a unit after {value}")
        if key in ("class", "level", "id", "category", "label"):
            if op not in ("=", "!="):
                unsupported(f"`{name} {op}`")
            f = getattr(self.w, "klass" if key == "class" else key)(value)
            return (lambda l: not f(l)) if op == "!=" else f
        return self.w.attribute(name, op, value)


class World:
    def __init__(self, run, mode):
        sem = json.load(open(os.path.join(run, "citymodel", "semantics.json")))
        self.ents = sem["entities"]
        fuse = os.path.join(run, "fuse", "labels.json")
        if os.path.exists(fuse):
            self.labels = json.load(open(fuse))["labels"]
        else:
            self.labels = [{"id": e["id"], "source": "city", "entity": e["id"], "class": None}
                           for e in self.ents]
        self.run = run
        ply = PlyData.read(os.path.join(run, mode, "semantic.ply"))
        self.label_of = np.asarray(ply["vertex"]["label"], dtype=np.int64)

    def ent(self, l):
        return self.ents[l["entity"]] if l["source"] == "city" else None

    def ancestors(self, e):
        while e is not None:
            yield e
            e = self.ents[e["parent"]] if e["parent"] is not None else None

    @staticmethod
    def norm_class(c):
        c = c.split(":")[-1].lower()
        return SAME.get(c, c)

    def klass(self, value):
        want = self.norm_class(value)
        wanted = ABSTRACT.get(want, {want})
        def f(l):
            e = self.ent(l)
            return e is not None and any(self.norm_class(a["class"]) in wanted
                                         for a in self.ancestors(e))
        return f

    def level(self, value):
        return lambda l: self.ent(l) is not None and self.ent(l)["level"] == value.lower()

    def id(self, value):
        return lambda l: self.ent(l) is not None and self.ent(l)["object_id"] == value

    def within(self, value):
        return lambda l: self.ent(l) is not None and any(a["object_id"] == value
                                                          for a in self.ancestors(self.ent(l)))

    def category(self, value):
        c = NAMES.index(value.lower())
        return lambda l: self.eval_class(l) == c

    def label(self, value):
        return lambda l: l["id"] == int(value)

    def eval_class(self, l):
        if l.get("class") is not None:
            return l["class"]
        # Without a fuse table: the documented mapping of an entity's class.
        e = self.ent(l)
        c = self.norm_class(e["class"])
        if c == "window":
            return 2
        if c == "door":
            return 3
        if any(self.norm_class(a["class"]) in ("buildinginstallation",
                                                "buildingconstructiveelement")
               for a in self.ancestors(e)):
            return 5
        return {"roofsurface": 1, "outerfloorsurface": 1, "groundsurface": 4}.get(c, 0)

    def attribute(self, name, op, value):
        ops = {"=": lambda a, b: a == b, "!=": lambda a, b: a != b, "<": lambda a, b: a < b,
               "<=": lambda a, b: a <= b, ">": lambda a, b: a > b, ">=": lambda a, b: a >= b}
        cmp = ops[op]

        def num(x):
            try:
                return float(x)
            except (TypeError, ValueError):
                return None

        def f(l):
            e = self.ent(l)
            if e is None:
                return False
            have = next((a["attributes"][name] for a in self.ancestors(e)
                         if name in a["attributes"]), None)
            if have is None:
                return False
            values = have if isinstance(have, list) else [have]
            if op == "!=":
                return all(not cmp_eq(v) for v in values)
            return any(match(v) for v in values)

        def match(v):
            a, b = num(v), num(value)
            if a is not None and b is not None:
                return cmp(a, b)
            return cmp(str(v), value)

        def cmp_eq(v):
            a, b = num(v), num(value)
            return a == b if a is not None and b is not None else str(v) == value
        return f

    def text(self, prompt):
        scene = json.load(open(os.path.join(self.run, "run.json")))["scene"]
        p = json.load(open(os.path.join(scene, "features", "prompts.json")))["prompts"]
        key = next((k for k in p if k.strip().lower() == prompt.strip().lower()), None)
        if key is None:
            unsupported(f"free text {prompt!r}")
        unit = lambda v: np.asarray(v, np.float64) / np.linalg.norm(v)
        q = unit(p[key])
        negs = [unit(v) for k, v in p.items() if k != key and unit(v) @ q < 0.8]
        feats = np.load(os.path.join(self.run, "fuse", "label_features.npy")).astype(np.float64)
        row = {l["id"]: i for i, l in enumerate(self.labels)}

        def f(l):
            v = feats[row[l["id"]]]
            n = np.linalg.norm(v)
            if n == 0:
                return False
            v = v / n
            rel = min(1.0 / (1.0 + math.exp(-10.0 * (v @ q - v @ m))) for m in negs)
            return rel >= 0.85
        return f


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("expr", nargs="+")
    ap.add_argument("--mode", choices=["lift", "train"])
    ap.add_argument("--indices", action="store_true", help="also list the selected Gaussians")
    a = ap.parse_args()
    mode = a.mode or ("train" if os.path.exists(os.path.join(a.run, "train", "gaussians.npy"))
                      else "lift")
    w = World(a.run, mode)
    out = {}
    for expr in a.expr:
        p = Parser(tokens(expr), w)
        f = p.expr()
        if p.i != len(p.t):
            unsupported(f"`{expr}` after term {p.i}")
        chosen = sorted(l["id"] for l in w.labels if f(l))
        sel = np.isin(w.label_of, chosen) & (w.label_of >= 0)
        out[expr] = {"labels": chosen, "gaussians": int(sel.sum())}
        if a.indices:
            out[expr]["indices"] = np.nonzero(sel)[0].tolist()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
