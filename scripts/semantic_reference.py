#!/usr/bin/env python3
"""Independent reference of `gs4city segment --semantic`'s per-pixel classes (docs/segment.md).

Written from the description in docs/segment.md, sharing no code with gs4city: the images are
decoded by Pillow, the network run by the pip package `onnxruntime`, everything else is NumPy.
For each image: tiles of the card's working size (an axis shorter than the tile: its length
rounded up to `multiple_of`, the last row/column repeated; longer: ceil((L - T) / (0.75 T)) + 1
tiles, origins round(k (L - T) / (n - 1))), each normalised by the card's steps in float64 then
cast to float32, run, logits resized to the tile (bilinear, half-pixel centres) where smaller,
softmax, averaged where tiles overlap, argmax. Writes <out>/<stem>.npy (uint16 H x W).

    python3 scripts/semantic_reference.py --model M.onnx --images DIR --out DIR [--threads N]
"""
import argparse
import json
import math
import os

import numpy as np
import onnxruntime as ort
from PIL import Image


def starts(length, tile):
    if length <= tile:
        return [0]
    stride = max(tile * 0.75, 1.0)
    n = math.ceil((length - tile) / stride) + 1
    return [int(round(k * (length - tile) / (n - 1))) for k in range(n)]


def normalise(v, card):
    x = v.astype(np.float64)
    mean = np.array(card["mean"], dtype=np.float64)
    std = np.array(card["std"], dtype=np.float64)
    for s in card["steps"]:
        if s == "mean":
            x = x - mean
        elif s == "std":
            x = x / std
        else:
            x = x / card["scale"]
    return x.astype(np.float32)


def resize(logits, oh, ow):
    c, ih, iw = logits.shape
    if (ih, iw) == (oh, ow):
        return logits

    def axis(o, i):
        s = np.maximum((np.arange(o) + 0.5) * i / o - 0.5, 0.0)
        a = np.minimum(np.floor(s).astype(int), i - 1)
        b = np.minimum(a + 1, i - 1)
        return a, b, (s - a).astype(np.float32)

    y0, y1, fy = axis(oh, ih)
    x0, x1, fx = axis(ow, iw)
    top = logits[:, y0][:, :, x0] * (1 - fx) + logits[:, y0][:, :, x1] * fx
    bot = logits[:, y1][:, :, x0] * (1 - fx) + logits[:, y1][:, :, x1] * fx
    return top * (1 - fy[:, None]) + bot * fy[:, None]


def classify(sess, card, rgb):
    h, w, _ = rgb.shape
    m = card.get("multiple_of", 1)
    th = min(card["tile"][0], -(-h // m) * m)
    tw = min(card["tile"][1], -(-w // m) * m)
    img = rgb[:, :, ::-1] if card["channel_order"] == "BGR" else rgb
    c = len(card["classes"])
    acc = np.zeros((c, h, w), dtype=np.float32)
    cnt = np.zeros((h, w), dtype=np.float32)
    inp = card.get("input") or sess.get_inputs()[0].name
    out = card.get("output") or sess.get_outputs()[0].name
    for y0 in starts(h, th):
        for x0 in starts(w, tw):
            ys = np.minimum(np.arange(y0, y0 + th), h - 1)
            xs = np.minimum(np.arange(x0, x0 + tw), w - 1)
            tile = normalise(img[ys][:, xs], card).transpose(2, 0, 1)[None]
            logits = sess.run([out], {inp: np.ascontiguousarray(tile)})[0][0]
            p = resize(logits.astype(np.float32), th, tw)
            if not card.get("output_probabilities", False):
                p = np.exp(p - p.max(axis=0, keepdims=True))
                p = p / p.sum(axis=0, keepdims=True)
            vh, vw = min(th, h - y0), min(tw, w - x0)
            acc[:, y0:y0 + vh, x0:x0 + vw] += p[:, :vh, :vw]
            cnt[y0:y0 + vh, x0:x0 + vw] += 1
    return np.argmax(acc / cnt, axis=0).astype(np.uint16)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--threads", type=int, default=0)
    a = ap.parse_args()
    card = json.load(open(os.path.splitext(a.model)[0] + ".json"))
    so = ort.SessionOptions()
    so.intra_op_num_threads = a.threads
    sess = ort.InferenceSession(a.model, so, providers=["CPUExecutionProvider"])
    os.makedirs(a.out, exist_ok=True)
    for name in sorted(os.listdir(a.images)):
        stem, ext = os.path.splitext(name)
        if ext.lower() not in (".png", ".jpg", ".jpeg"):
            continue
        rgb = np.asarray(Image.open(os.path.join(a.images, name)).convert("RGB"))
        np.save(os.path.join(a.out, stem + ".npy"), classify(sess, card, rgb))


if __name__ == "__main__":
    main()
