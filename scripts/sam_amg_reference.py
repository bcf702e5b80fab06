#!/usr/bin/env python3
"""Independent reference of `gs4city segment`: SAM's automatic mask generation in NumPy, the
networks run by onnxruntime. Written from the SAM paper's description of automatic mask
generation and the documented behaviour of `SamAutomaticMaskGenerator` (one crop, no crop
layers), not from the Rust code:

  image (H x W x 3 uint8, read from a .npy) -> area-downscaled by --scale (the reference
  pipeline's default_scale 0.25) -> longest side resized to 1024 (bilinear, rounded to uint8)
  -> normalised by SAM's pixel mean/std, zero-padded to 1024 x 1024 -> encoder.onnx;
  an n x n point grid (cell centres) in the downscaled image, mapped to the 1024 frame, decoded
  in batches with a padding point (label -1) -> the three multimask outputs per point ->
  predicted IoU > pred_iou_thresh -> stability score (IoU of the masks thresholded at +1 and -1)
  >= stability_score_thresh -> binary masks (logit > 0) -> box NMS (score = predicted IoU,
  box IoU > box_nms_thresh suppresses) -> optional small-region removal (holes, then islands,
  8-connected; changed masks rank after unchanged ones in a second box NMS) -> masks upscaled to
  H x W by nearest neighbour (source index floor(i * h / H)) -> COCO RLE (pycocotools).

Writes the SAM JSON list (segmentation, area, bbox, predicted_iou, stability_score,
point_coords, crop_box).
Usage: sam_amg_reference.py --model DIR --image IMG.npy --out OUT.json [--points-per-side 32]
       [--pred-iou-thresh 0.88] [--stability-score-thresh 0.95] [--box-nms-thresh 0.7]
       [--min-mask-region-area 0] [--scale 0.25] [--points-per-batch 64] [--defect D]

--defect makes the reference deliberately wrong, to show that a bound against it notices a small
defect: `shift` (the image one pixel to the right before encoding), `mean` (CLIP's pixel mean,
122.8 116.7 104.1, in place of SAM's), `bgr` (the colour channels swapped).
"""
import argparse
import json
import os

import numpy as np
import onnxruntime as ort
from pycocotools import mask as mask_utils
from scipy import ndimage

MEAN = np.array([123.675, 116.28, 103.53])
STD = np.array([58.395, 57.12, 57.375])


def round_half_even(x):
    return int(np.rint(x))


def area_resize(img, out_w, out_h):
    """Box-filter downscaling: each output pixel is the overlap-weighted mean of the input."""
    h, w = img.shape[:2]

    def weights(n_in, n_out):
        s = n_in / n_out
        m = np.zeros((n_out, n_in))
        for o in range(n_out):
            a, b = o * s, (o + 1) * s
            for i in range(int(np.floor(a)), min(int(np.ceil(b)), n_in)):
                m[o, i] = max(0.0, min(b, i + 1) - max(a, i))
            m[o] /= m[o].sum()
        return m

    wy, wx = weights(h, out_h), weights(w, out_w)
    tmp = np.tensordot(wy, img.astype(np.float64), axes=(1, 0))  # (out_h, w, c)
    out = np.matmul(wx[None], tmp)  # (out_h, out_w, c)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def bilinear_resize(img, out_w, out_h):
    """Half-pixel-centre bilinear resampling with edge clamping, float, rounded to uint8."""
    h, w = img.shape[:2]

    def taps(n_in, n_out):
        c = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
        c = np.clip(c, 0, None)
        i0 = np.minimum(np.floor(c).astype(int), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        f = c - i0
        return i0, i1, f

    y0, y1, fy = taps(h, out_h)
    x0, x1, fx = taps(w, out_w)
    im = img.astype(np.float64)
    top = im[y0][:, x0] * (1 - fx)[None, :, None] + im[y0][:, x1] * fx[None, :, None]
    bot = im[y1][:, x0] * (1 - fx)[None, :, None] + im[y1][:, x1] * fx[None, :, None]
    out = top * (1 - fy)[:, None, None] + bot * fy[:, None, None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def mask_box(m):
    """SAM's box of a mask: [x0, y0, x1, y1] with inclusive maxima; empty -> zeros."""
    ys = np.where(m.any(axis=1))[0]
    xs = np.where(m.any(axis=0))[0]
    if len(xs) == 0:
        return np.zeros(4)
    return np.array([xs[0], ys[0], xs[-1], ys[-1]], dtype=np.float64)


def nms(boxes, scores, thresh):
    """Greedy NMS: highest score first (ties by index), drop boxes with IoU > thresh."""
    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    keep, dead = [], np.zeros(len(scores), bool)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    for a, i in enumerate(order):
        if dead[i]:
            continue
        keep.append(i)
        for j in order[a + 1:]:
            if dead[j]:
                continue
            iw = max(0.0, min(boxes[i, 2], boxes[j, 2]) - max(boxes[i, 0], boxes[j, 0]))
            ih = max(0.0, min(boxes[i, 3], boxes[j, 3]) - max(boxes[i, 1], boxes[j, 1]))
            inter = iw * ih
            union = area[i] + area[j] - inter
            if union > 0 and inter / union > thresh:
                dead[j] = True
    return keep


def remove_small_regions(m, min_area, holes):
    work = ~m if holes else m
    regions, n = ndimage.label(work, structure=np.ones((3, 3), int))
    sizes = ndimage.sum(np.ones_like(regions), regions, index=np.arange(1, n + 1))
    small = [i + 1 for i, s in enumerate(sizes) if s < min_area]
    if not small:
        return m, False
    if holes:
        return ~work | np.isin(regions, small), True
    keep = [i for i in range(1, n + 1) if i not in small]
    if not keep:
        keep = [int(np.argmax(sizes)) + 1]
    return np.isin(regions, keep), True


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--image", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--points-per-side", type=int, default=32)
    ap.add_argument("--pred-iou-thresh", type=float, default=0.88)
    ap.add_argument("--stability-score-thresh", type=float, default=0.95)
    ap.add_argument("--box-nms-thresh", type=float, default=0.7)
    ap.add_argument("--min-mask-region-area", type=int, default=0)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--points-per-batch", type=int, default=64)
    ap.add_argument("--defect", choices=["shift", "mean", "bgr"])
    a = ap.parse_args()

    full = np.load(a.image)
    if a.defect == "shift":
        full = np.concatenate([full[:, :1], full[:, :-1]], axis=1)
    elif a.defect == "bgr":
        full = np.ascontiguousarray(full[..., ::-1])
    mean = np.array([122.77, 116.75, 104.09]) if a.defect == "mean" else MEAN
    H, W = full.shape[:2]
    w, h = round_half_even(W * a.scale), round_half_even(H * a.scale)
    img = full if (w, h) == (W, H) else area_resize(full, w, h)
    s = 1024.0 / max(h, w)
    nh, nw = int(h * s + 0.5), int(w * s + 0.5)
    x = bilinear_resize(img, nw, nh).astype(np.float64)
    x = (x - mean) / STD
    inp = np.zeros((1, 3, 1024, 1024), np.float32)
    inp[0, :, :nh, :nw] = x.transpose(2, 0, 1)
    opts = ort.SessionOptions()
    enc = ort.InferenceSession(os.path.join(a.model, "encoder.onnx"), opts)
    dec = ort.InferenceSession(os.path.join(a.model, "decoder.onnx"), opts)
    emb = enc.run(None, {enc.get_inputs()[0].name: inp})[0]

    n = a.points_per_side
    side = np.linspace(1 / (2 * n), 1 - 1 / (2 * n), n)
    grid = np.stack([np.tile(side[None, :], (n, 1)), np.tile(side[:, None], (1, n))], -1).reshape(-1, 2)
    points = grid * np.array([w, h])
    masks, ious, stabs, pts = [], [], [], []
    iou_t = np.float32(a.pred_iou_thresh)
    for b0 in range(0, len(points), a.points_per_batch):
        p = points[b0:b0 + a.points_per_batch]
        q = p * np.array([nw / w, nh / h])
        coords = np.zeros((len(p), 2, 2), np.float32)
        coords[:, 0] = q
        labels = np.tile(np.array([[1.0, -1.0]], np.float32), (len(p), 1))
        out = dec.run(None, {
            "image_embeddings": emb, "point_coords": coords, "point_labels": labels,
            "mask_input": np.zeros((1, 1, 256, 256), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([h, w], np.float32)})
        logits, iou = out[0], out[1]
        if logits.shape[1] == 4:
            logits, iou = logits[:, 1:], iou[:, 1:]
        for i in range(len(p)):
            for k in range(logits.shape[1]):
                if not iou[i, k] > iou_t:
                    continue
                lg = logits[i, k]
                union = int((lg > -1.0).sum())
                inter = int((lg > 1.0).sum())
                stab = inter / union if union > 0 else 0.0
                if not stab >= a.stability_score_thresh:
                    continue
                masks.append(lg > 0.0)
                ious.append(float(iou[i, k]))
                stabs.append(stab)
                pts.append(p[i])
    if masks:
        boxes = np.stack([mask_box(m) for m in masks])
        keep = nms(boxes, ious, a.box_nms_thresh)
        masks = [masks[i] for i in keep]
        ious, stabs, pts = [ious[i] for i in keep], [stabs[i] for i in keep], [pts[i] for i in keep]
    if a.min_mask_region_area > 0 and masks:
        new, scores = [], []
        for m in masks:
            m2, c1 = remove_small_regions(m, a.min_mask_region_area, True)
            m2, c2 = remove_small_regions(m2, a.min_mask_region_area, False)
            new.append(m2)
            scores.append(0.0 if (c1 or c2) else 1.0)
        boxes = np.stack([mask_box(m) for m in new])
        keep = nms(boxes, scores, a.box_nms_thresh)
        masks = [new[i] for i in keep]
        ious, stabs, pts = [ious[i] for i in keep], [stabs[i] for i in keep], [pts[i] for i in keep]

    ys = (np.arange(H) * h) // H
    xs = (np.arange(W) * w) // W
    anns = []
    for m, iou, st, p in zip(masks, ious, stabs, pts):
        big = m[ys][:, xs]
        rle = mask_utils.encode(np.asfortranarray(big.astype(np.uint8)))
        box = mask_box(big)
        anns.append({
            "segmentation": {"size": [H, W], "counts": rle["counts"].decode()},
            "area": int(big.sum()),
            "bbox": [int(box[0]), int(box[1]), int(box[2] - box[0]), int(box[3] - box[1])],
            "predicted_iou": iou, "stability_score": st,
            "point_coords": [[float(p[0] * W / w), float(p[1] * H / h)]],
            "crop_box": [0, 0, W, H]})
    with open(a.out, "w") as f:
        json.dump(anns, f)
    print(f"{len(anns)} masks")


if __name__ == "__main__":
    main()
