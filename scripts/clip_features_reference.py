#!/usr/bin/env python3
"""Independent reference of `gs4city features` (CLIP features of SAM masks), written from the
description of the reference preprocessing (LangSplat's crop: the mask's bounding box padded to
a square, outside-mask pixels filled; CLIP's normalisation) and of CLIP's tokenizer, not from
the Rust code. The networks run in the pip package onnxruntime; the tokenizer is the
`tokenizers` library configured as Hugging Face's CLIP converter does (NFC, whitespace runs to
one space, lowercase; CLIP's split pattern, byte-level, `</w>` word ends); masks are decoded by
pycocotools.

  tokens   --model DIR --texts T.json --out O.json     ids [77] per text (0-padded)
  features --model DIR --image I.npy --masks M.json --texts T.json --out DIR [--defect D]
           -> DIR/features.npy (one unit row per mask), DIR/prompts.json ({text: unit vector})

--defect makes the reference deliberately wrong, to show that a bound against it notices a small
defect: `crop-shift` (the mask, and so its box, one pixel to the right), `mean` (ImageNet's mean
0.485, 0.456, 0.406 in place of CLIP's), `bgr` (the colour channels swapped).

The crop (docs/features.md): tight box x0..x1, y0..y1 of the mask; side L = max(w, h); an L x L
canvas of grey (123, 117, 104) with the box at ((L-w)//2, (L-h)//2), mask pixels copied;
bilinear resize to 224 (half-pixel centres, edges repeated, float, rounded to 8 bits); /255,
minus CLIP's mean, over its std; channels first.
"""
import argparse
import json
import os

import numpy as np
import onnxruntime as ort
from pycocotools import mask as mask_utils

MEAN = np.array([0.48145466, 0.4578275, 0.40821073])
STD = np.array([0.26862954, 0.26130258, 0.27577711])
GREY = np.array([123, 117, 104], np.uint8)
CONTEXT = 77


def tokenizer(model):
    from tokenizers import Regex, Tokenizer, models, normalizers, pre_tokenizers
    bpe = models.BPE.from_file(os.path.join(model, "vocab.json"), os.path.join(model, "merges.txt"),
                               end_of_word_suffix="</w>", continuing_subword_prefix="",
                               unk_token="<|endoftext|>", fuse_unk=False)
    tok = Tokenizer(bpe)
    tok.normalizer = normalizers.Sequence([
        normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()])
    tok.pre_tokenizer = pre_tokenizers.Sequence([
        pre_tokenizers.Split(Regex(r"""'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""),
                             behavior="removed", invert=True),
        pre_tokenizers.ByteLevel(add_prefix_space=False)])
    tok.add_special_tokens(["<|startoftext|>", "<|endoftext|>"])
    sot, eot = tok.token_to_id("<|startoftext|>"), tok.token_to_id("<|endoftext|>")

    def ids(text):
        v = [sot] + tok.encode(text, add_special_tokens=False).ids + [eot]
        if len(v) > CONTEXT:
            v = v[:CONTEXT]
            v[-1] = eot
        return v + [0] * (CONTEXT - len(v))
    return ids


def bilinear(img, side):
    """Bilinear resize of an H x W x 3 uint8 image to side x side (half-pixel centres)."""
    def taps(n_in):
        f = (np.arange(side) + 0.5) * (n_in / side) - 0.5
        i0 = np.floor(f).astype(np.int64)
        w = f - i0
        lo = i0 < 0
        w[lo], i0[lo] = 0.0, 0
        hi = i0 >= n_in - 1
        w[hi], i0[hi] = 0.0, n_in - 1
        return i0, np.minimum(i0 + 1, n_in - 1), w.astype(np.float32)

    x = img.astype(np.float32)
    y0, y1, wy = taps(img.shape[0])
    x = x[y0] * (1 - wy)[:, None, None] + x[y1] * wy[:, None, None]
    x0, x1, wx = taps(img.shape[1])
    x = x[:, x0] * (1 - wx)[None, :, None] + x[:, x1] * wx[None, :, None]
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def crop(rgb, m, side, defect=None):
    if defect == "bgr":
        rgb = rgb[..., ::-1]
    if defect == "crop-shift":  # the mask, and so its box, one pixel to the right
        m = np.concatenate([np.zeros_like(m[:, :1]), m[:, :-1]], axis=1)
    ys, xs = np.nonzero(m)
    if len(ys) == 0:
        sq = np.broadcast_to(GREY, (1, 1, 3)).copy()
    else:
        y0, y1, x0, x1 = ys.min(), ys.max(), xs.min(), xs.max()
        h, w = y1 - y0 + 1, x1 - x0 + 1
        L = max(h, w)
        sq = np.broadcast_to(GREY, (L, L, 3)).copy()
        box = np.where(m[y0:y1 + 1, x0:x1 + 1, None], rgb[y0:y1 + 1, x0:x1 + 1], GREY)
        oy, ox = (L - h) // 2, (L - w) // 2
        sq[oy:oy + h, ox:ox + w] = box
    if sq.shape[0] != side:
        sq = bilinear(sq, side)
    mean = np.array([0.485, 0.456, 0.406]) if defect == "mean" else MEAN
    x = (sq.astype(np.float64) / 255.0 - mean) / STD
    return x.transpose(2, 0, 1).astype(np.float32)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["tokens", "features"])
    ap.add_argument("--model", required=True)
    ap.add_argument("--texts", required=True)
    ap.add_argument("--image")
    ap.add_argument("--masks")
    ap.add_argument("--out", required=True)
    ap.add_argument("--defect", choices=["crop-shift", "mean", "bgr"])
    a = ap.parse_args()
    texts = json.load(open(a.texts, encoding="utf-8"))
    ids = tokenizer(a.model)
    if a.what == "tokens":
        json.dump([ids(t) for t in texts], open(a.out, "w"))
        return
    os.makedirs(a.out, exist_ok=True)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    image = ort.InferenceSession(os.path.join(a.model, "clip_image.onnx"), so)
    text = ort.InferenceSession(os.path.join(a.model, "clip_text.onnx"), so)
    rgb = np.load(a.image)
    masks = json.load(open(a.masks))
    rows = []
    for m in masks:
        seg = dict(m["segmentation"])
        if isinstance(seg["counts"], str):
            seg["counts"] = seg["counts"].encode()
        else:
            seg = mask_utils.frPyObjects(seg, *seg["size"])
        dec = mask_utils.decode(seg).astype(bool)
        x = crop(rgb, dec, 224, a.defect)[None]
        rows.append(image.run(None, {image.get_inputs()[0].name: x})[0][0])
    np.save(os.path.join(a.out, "features.npy"), unit(np.array(rows)).astype(np.float32))
    prompts = {}
    for t in texts:
        v = text.run(None, {"input_ids": np.array([ids(t)], np.int64)})[0][0]
        prompts[t] = unit(v).tolist()
    json.dump(prompts, open(os.path.join(a.out, "prompts.json"), "w"))


if __name__ == "__main__":
    main()
