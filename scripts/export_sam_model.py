#!/usr/bin/env python3
"""Lays out a gs4city SAM-family model folder (docs/segment.md) from a published checkpoint:

  encoder.onnx  the image encoder, [1, 3, 1024, 1024] -> image_embeddings [1, 256, 64, 64]
  decoder.onnx  the prompt encoder + mask decoder as segment-anything's own
                scripts/export_onnx_model.py exports it (SamOnnxModel, all four mask outputs,
                opset 17, dynamic num_points, batch 1)
  model.json    {"family", "size", "checkpoint"}

Needs torch and the model's own package, neither of which gs4city needs:
  pip install torch torchvision segment-anything      # SAM ViT-B/L/H (sam_vit_b_01ec64.pth, ...)
  pip install git+https://github.com/ChaoningZhang/MobileSAM   # MobileSAM (mobile_sam.pt, --model-type vit_t)

Usage:
  export_sam_model.py --checkpoint sam_vit_b_01ec64.pth --model-type vit_b --out models/sam_b
  export_sam_model.py --checkpoint mobile_sam.pt --model-type vit_t --out models/mobile_sam

--random-init builds the network with seeded random weights instead of a checkpoint: for
gs4city's own test of the real export's structure (tests/segment.rs, ignored by default), never
for masks anyone should use.
"""
import argparse
import json
import os
import sys
import warnings


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint")
    ap.add_argument("--model-type", required=True, help="vit_b, vit_l, vit_h (SAM) or vit_t (MobileSAM)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--random-init", action="store_true", help="seeded random weights (tests only)")
    a = ap.parse_args()
    if (a.checkpoint is None) == (not a.random_init):
        ap.error("give --checkpoint FILE (or, for tests, --random-init)")
    try:
        import torch
    except ImportError:
        sys.exit("export_sam_model.py: torch is not installed (pip install torch torchvision)")
    try:
        if a.model_type == "vit_t":
            from mobile_sam import sam_model_registry
            from mobile_sam.utils.onnx import SamOnnxModel
            family = "mobile_sam"
        else:
            from segment_anything import sam_model_registry
            from segment_anything.utils.onnx import SamOnnxModel
            family = "sam"
    except ImportError as e:
        sys.exit(f"export_sam_model.py: {e}: install the model's package (see --help)")
    if a.model_type not in sam_model_registry:
        sys.exit(f"export_sam_model.py: unknown --model-type {a.model_type} "
                 f"(known: {', '.join(k for k in sam_model_registry if k != 'default')})")
    if a.checkpoint is not None and not os.path.isfile(a.checkpoint):
        sys.exit(f"export_sam_model.py: no checkpoint file {a.checkpoint}")
    torch.manual_seed(0)
    sam = sam_model_registry[a.model_type](checkpoint=a.checkpoint).eval()
    os.makedirs(a.out, exist_ok=True)

    dec = SamOnnxModel(model=sam, return_single_mask=False)
    embed_size = sam.prompt_encoder.image_embedding_size
    dummy = {
        "image_embeddings": torch.randn(1, sam.prompt_encoder.embed_dim, *embed_size),
        "point_coords": torch.randint(0, 1024, (1, 5, 2)).float(),
        "point_labels": torch.randint(0, 4, (1, 5)).float(),
        "mask_input": torch.randn(1, 1, *[4 * x for x in embed_size]),
        "has_mask_input": torch.tensor([1.0]),
        "orig_im_size": torch.tensor([1500.0, 2250.0]),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            dec, tuple(dummy.values()), os.path.join(a.out, "decoder.onnx"),
            export_params=True, opset_version=17, do_constant_folding=True,
            input_names=list(dummy), output_names=["masks", "iou_predictions", "low_res_masks"],
            dynamic_axes={"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}})
        torch.onnx.export(
            sam.image_encoder, torch.zeros(1, 3, 1024, 1024), os.path.join(a.out, "encoder.onnx"),
            input_names=["image"], output_names=["image_embeddings"], opset_version=17)
    info = {"family": family, "size": a.model_type,
            "checkpoint": os.path.basename(a.checkpoint) if a.checkpoint else None}
    if a.random_init:
        info["note"] = "RANDOM weights (export_sam_model.py --random-init): for tests only"
    with open(os.path.join(a.out, "model.json"), "w") as f:
        json.dump(info, f, indent=1)
    print(f"wrote {a.out}/encoder.onnx, decoder.onnx, model.json")


if __name__ == "__main__":
    main()
