#!/usr/bin/env python3
"""Lays out a gs4city CLIP model folder (docs/features.md) from a Hugging Face CLIP checkpoint:

  clip_image.onnx   CLIPVisionModelWithProjection: pixel_values [B, 3, 224, 224] -> image_embeds [B, D]
  clip_text.onnx    CLIPTextModelWithProjection: input_ids [B, 77] int64 -> text_embeds [B, D]
  vocab.json, merges.txt   the checkpoint's BPE

Needs torch and transformers, which gs4city itself does not:
  pip install torch transformers
  huggingface-cli download openai/clip-vit-base-patch32 --local-dir clip-b32   # or any CLIP folder
  export_clip_model.py --checkpoint clip-b32 --out models/clip

--random-init builds ViT-B/32 with seeded random weights and takes the BPE files from
--vocab-from DIR: for gs4city's own test of Hugging Face's graphs (tests/features.rs, ignored by
default), never for features anyone should use.
"""
import argparse
import os
import shutil
import sys
import warnings


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", help="a Hugging Face CLIP folder or hub id")
    ap.add_argument("--out", required=True)
    ap.add_argument("--random-init", action="store_true", help="seeded random ViT-B/32 (tests only)")
    ap.add_argument("--vocab-from", help="with --random-init: a folder with vocab.json and merges.txt")
    a = ap.parse_args()
    if (a.checkpoint is None) == (not a.random_init):
        ap.error("give --checkpoint DIR (or, for tests, --random-init --vocab-from DIR)")
    if a.random_init and not a.vocab_from:
        ap.error("--random-init needs --vocab-from DIR")
    try:
        import torch
        from transformers import (CLIPTextConfig, CLIPTextModelWithProjection, CLIPTokenizer,
                                  CLIPVisionConfig, CLIPVisionModelWithProjection)
    except ImportError as e:
        sys.exit(f"export_clip_model.py: {e}: pip install torch transformers")
    os.makedirs(a.out, exist_ok=True)
    if a.random_init:
        torch.manual_seed(0)
        vis = CLIPVisionModelWithProjection(CLIPVisionConfig(
            hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
            image_size=224, patch_size=32, projection_dim=512))
        # eos_token_id 2: pooling at the largest id, <|endoftext|>, as the published config does
        txt = CLIPTextModelWithProjection(CLIPTextConfig(
            vocab_size=49408, hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
            num_attention_heads=8, max_position_embeddings=77, projection_dim=512, eos_token_id=2))
        for f in ("vocab.json", "merges.txt"):
            shutil.copy(os.path.join(a.vocab_from, f), os.path.join(a.out, f))
    else:
        vis = CLIPVisionModelWithProjection.from_pretrained(a.checkpoint)
        txt = CLIPTextModelWithProjection.from_pretrained(a.checkpoint)
        CLIPTokenizer.from_pretrained(a.checkpoint).save_vocabulary(a.out)
    vis.eval().config.return_dict = False
    txt.eval().config.return_dict = False
    side = vis.config.image_size
    ctx = txt.config.max_position_embeddings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(vis, (torch.zeros(2, 3, side, side),), os.path.join(a.out, "clip_image.onnx"),
                          input_names=["pixel_values"], output_names=["image_embeds"],
                          dynamic_axes={"pixel_values": {0: "batch"}, "image_embeds": {0: "batch"}},
                          opset_version=17)
        torch.onnx.export(txt, (torch.zeros(2, ctx, dtype=torch.int64),), os.path.join(a.out, "clip_text.onnx"),
                          input_names=["input_ids"], output_names=["text_embeds"],
                          dynamic_axes={"input_ids": {0: "batch"}, "text_embeds": {0: "batch"}},
                          opset_version=17)
    print(f"wrote {a.out}/clip_image.onnx, clip_text.onnx, vocab.json, merges.txt")


if __name__ == "__main__":
    main()
