#!/usr/bin/env python3
"""Writes a SAM-family model folder (ONNX opset 17) with RANDOM weights for tests and benchmarks (no published
weights can be downloaded here). The graphs have the real architectures' input/output signatures
and, for the `mobilesam` and `vit_b` sizes, their layer counts, widths, token counts and window
sizes, so their compute matches the real networks (compute does not depend on weight values):

  encoder.onnx  image [1,3,1024,1024] (SAM-normalised, zero-padded bottom/right)
                -> image_embeddings [1,256,64,64]
  decoder.onnx  SAM's ONNX export signature (segment_anything/utils/onnx.py, return_single_mask
                off): image_embeddings [1,256,64,64], point_coords [B,N,2] (1024-frame pixels),
                point_labels [B,N], mask_input [1,1,256,256], has_mask_input [1], orig_im_size [2]
                -> masks [B,4,H,W] (logits at orig_im_size), iou_predictions [B,4],
                   low_res_masks [B,4,256,256]
  model.json    {"family": ..., "size": ..., "generated": true}

Encoders: `vit_b` = SAM ViT-B (patch 16, 768 wide, 12 blocks, 12 heads, 14x14 windows, global
attention in blocks 2/5/8/11, MLP x4, neck 768->256 conv1x1 + conv3x3); `mobilesam` = TinyViT-5M
as MobileSAM uses it (conv stem to 256x256, MBConv stage 64 wide, then windowed-attention
stages 128/160/320 wide, depths 2/6/2, heads 4/5/10, windows 7/14/7, at 128x128/64x64/64x64,
neck 320->256); `tiny` = a small encoder for the tests. Relative position terms of the attention
are left out (their compute is negligible). The decoder is SAM's (two-way transformer of depth 2,
256 wide, 8 heads, MLP 2048, attention downsample 2, upscaling to 256x256 with 32 channels,
hypernetwork MLPs, IoU head) in every size except `tiny` (depth 1, downsample 8, 8 channels).

With `--clip tiny|vit_b32` it writes a CLIP model folder instead (gs4city features):

  clip_image.onnx  pixel_values [B,3,224,224] (CLIP-normalised) -> image_embeds [B,E]
  clip_text.onnx   input_ids [B,77] int64 (0-padded) -> text_embeds [B,E] (the state at the
                   argmax id, <|endoftext|>)
  vocab.json, merges.txt  a small byte-level BPE (a few hundred merges) trained with the
                   `tokenizers` library on a built-in text, in CLIP's vocabulary layout

`vit_b32` has OpenAI CLIP ViT-B/32's sizes (image: patch 32, 768 wide, 12 layers, 12 heads;
text: 512 wide, 12 layers, 8 heads, 49408 tokens; embedding 512; 151 M parameters); `tiny` is
a small one for the tests. The blocks use GELU (CLIP: QuickGELU; the same compute).

Usage: python3 scripts/make_test_models.py --size tiny|mobilesam|vit_b --out DIR [--seed N]
       python3 scripts/make_test_models.py --clip tiny|vit_b32 --out DIR [--seed N]
"""
import argparse
import json
import math
import os

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


class G:
    """A small graph builder: every op returns the name of its output."""

    def __init__(self, seed):
        self.nodes, self.inits, self.n = [], [], 0
        self.rng = np.random.default_rng(seed)

    def name(self, p):
        self.n += 1
        return f"{p}_{self.n}"

    def const(self, arr, p="c", exact=None):
        """An initializer; `exact` names it as torch.onnx.export names a module's parameter
        (`mask_decoder.….bias`), which gs4city's native SAM decoder reads weights by."""
        n = exact or self.name(p)
        self.inits.append(numpy_helper.from_array(np.asarray(arr), n))
        return n

    def w(self, shape, std, exact=None):
        return self.const(self.rng.normal(0.0, std, size=shape).astype(np.float32), "w", exact)

    def op(self, t, ins, p=None, **attrs):
        out = self.name(p or t.lower())
        self.nodes.append(helper.make_node(t, ins, [out], **attrs))
        return out

    def i64(self, v):
        return self.const(np.array(v, dtype=np.int64), "shape")

    def f32(self, v):
        return self.const(np.array(v, dtype=np.float32), "f")

    # layers
    def linear(self, x, din, dout, bias=True, gain=1.0, bias_value=None, path=None):
        """x·W + b as torch exports nn.Linear on a 3-D input: MatMul with the folded [in, out]
        weight, then Add of the bias (named `path.bias` when a module path is given)."""
        y = self.op("MatMul", [x, self.w((din, dout), gain / math.sqrt(din))])
        if bias:
            if bias_value is None:
                # small random biases (zeros would hide a bias read from the wrong place)
                b = (0.02 * self.rng.normal(size=dout)).astype(np.float32) if path else np.zeros(dout, np.float32)
            else:
                b = bias_value
            y = self.op("Add", [y, self.const(np.asarray(b, np.float32), "b",
                                              f"{path}.bias" if path else None)])
        return y

    def conv(self, x, cin, cout, k, stride=1, pad=0, groups=1):
        w = self.w((cout, cin // groups, k, k), 1.0 / math.sqrt(cin // groups * k * k))
        b = self.const(np.zeros(cout, np.float32), "b")
        return self.op("Conv", [x, w, b], kernel_shape=[k, k], strides=[stride, stride],
                       pads=[pad] * 4, group=groups)

    def conv_t(self, x, cin, cout, path=None):
        w = self.w((cin, cout, 2, 2), 1.0 / math.sqrt(cin), f"{path}.weight" if path else None)
        b = self.const((0.02 * self.rng.normal(size=cout)).astype(np.float32), "b",
                       f"{path}.bias" if path else None)
        return self.op("ConvTranspose", [x, w, b], kernel_shape=[2, 2], strides=[2, 2])

    def layernorm(self, x, dim, axis=-1, path=None):
        """LayerNorm over `axis` written out (ReduceMean, Sub, Mul, Sqrt, Div)."""
        mu = self.op("ReduceMean", [x], axes=[axis], keepdims=1)
        d = self.op("Sub", [x, mu])
        var = self.op("ReduceMean", [self.op("Mul", [d, d])], axes=[axis], keepdims=1)
        y = self.op("Div", [d, self.op("Sqrt", [self.op("Add", [var, self.f32(1e-6)])])])
        shape = [dim] if axis == -1 else [dim, 1, 1]
        g = self.const((1.0 + 0.1 * self.rng.normal(size=shape)).astype(np.float32), "ln_g",
                       f"{path}.weight" if path else None)
        b = self.const((0.1 * self.rng.normal(size=shape)).astype(np.float32), "ln_b",
                       f"{path}.bias" if path else None)
        return self.op("Add", [self.op("Mul", [y, g]), b])

    def layernorm_op(self, x, dim, path=None):
        """nn.LayerNorm over the last axis as torch exports it at opset ≥ 17: one
        LayerNormalization node (eps 1e-5, torch's default)."""
        g = self.const((1.0 + 0.1 * self.rng.normal(size=[dim])).astype(np.float32), "ln_g",
                       f"{path}.weight" if path else None)
        b = self.const((0.1 * self.rng.normal(size=[dim])).astype(np.float32), "ln_b",
                       f"{path}.bias" if path else None)
        return self.op("LayerNormalization", [x, g, b], axis=-1, epsilon=1e-5)

    def gelu(self, x):
        e = self.op("Erf", [self.op("Div", [x, self.f32(math.sqrt(2.0))])])
        return self.op("Mul", [self.op("Mul", [x, self.op("Add", [e, self.f32(1.0)])]), self.f32(0.5)])

    def reshape(self, x, shape):
        return self.op("Reshape", [x, self.i64(shape)])

    def attention(self, q_in, k_in, v_in, dim, heads, inner=None, qlen=-1, klen=-1, mask=None,
                  path=None):
        """Multi-head attention on [B, L, dim] inputs (B may be broadcast); projections to `inner`;
        `mask` an additive [L, L] constant (CLIP's causal text mask)."""
        inner = inner or dim
        dh = inner // heads
        sub = (lambda n: f"{path}.{n}") if path else (lambda n: None)
        q = self.linear(q_in, dim, inner, path=sub("q_proj"))
        k = self.linear(k_in, dim, inner, path=sub("k_proj"))
        v = self.linear(v_in, dim, inner, path=sub("v_proj"))

        def split(t, n):
            return self.op("Transpose", [self.reshape(t, [0, n, heads, dh])], perm=[0, 2, 1, 3])

        q, k, v = split(q, qlen), split(k, klen), split(v, klen)
        kt = self.op("Transpose", [k], perm=[0, 1, 3, 2])
        s = self.op("Mul", [self.op("MatMul", [q, kt]), self.f32(1.0 / math.sqrt(dh))])
        if mask is not None:
            s = self.op("Add", [s, mask])
        a = self.op("Softmax", [s], axis=-1)
        o = self.op("Transpose", [self.op("MatMul", [a, v])], perm=[0, 2, 1, 3])
        return self.linear(self.reshape(o, [0, qlen, inner]), inner, dim, path=sub("out_proj"))

    def vit_block(self, x, h, w, dim, heads, window, mlp_ratio=4.0, mask=None):
        """Pre-norm transformer block on x [1, h*w, dim] (any batch with window 0); window 0 =
        global attention, `mask` its additive attention mask."""
        y = self.layernorm(x, dim)
        if window == 0:
            y = self.attention(y, y, y, dim, heads, mask=mask)
        else:
            ph, pw = -h % window, -w % window
            hp, wp = h + ph, w + pw
            y = self.reshape(y, [1, h, w, dim])
            # zero padding as Concat with zeros (= Pad mode constant, which candle-onnx lacks)
            if ph:
                y = self.op("Concat", [y, self.const(np.zeros((1, ph, w, dim), np.float32), "pad")], axis=1)
            if pw:
                y = self.op("Concat", [y, self.const(np.zeros((1, hp, pw, dim), np.float32), "pad")], axis=2)
            nh, nw = hp // window, wp // window
            y = self.reshape(y, [1, nh, window, nw, window, dim])
            y = self.op("Transpose", [y], perm=[0, 1, 3, 2, 4, 5])
            y = self.reshape(y, [nh * nw, window * window, dim])
            y = self.attention(y, y, y, dim, heads, qlen=window * window, klen=window * window)
            y = self.reshape(y, [1, nh, nw, window, window, dim])
            y = self.op("Transpose", [y], perm=[0, 1, 3, 2, 4, 5])
            y = self.reshape(y, [1, hp, wp, dim])
            if ph or pw:
                y = self.op("Slice", [y, self.i64([0, 0]), self.i64([h, w]), self.i64([1, 2])])
            y = self.reshape(y, [1, h * w, dim])
        x = self.op("Add", [x, y])
        hidden = int(dim * mlp_ratio)
        y = self.layernorm(x, dim)
        y = self.linear(self.gelu(self.linear(y, dim, hidden)), hidden, dim)
        return self.op("Add", [x, y])

    def neck(self, x, dim, side=64):
        """[1, side*side, dim] tokens -> SAM's neck -> [1, 256, side, side]."""
        x = self.op("Transpose", [self.reshape(x, [1, side, side, dim])], perm=[0, 3, 1, 2])
        x = self.layernorm(self.conv(x, dim, 256, 1), 256, axis=1)
        x = self.layernorm(self.conv(x, 256, 256, 3, pad=1), 256, axis=1)
        return x


def encoder(size, seed):
    g = G(seed)
    x = "image"
    if size in ("tiny", "vit_b"):
        dim, depth, heads, window, glob = {
            "tiny": (32, 1, 2, 8, ()),
            "vit_b": (768, 12, 12, 14, (2, 5, 8, 11)),
        }[size]
        x = g.conv(x, 3, dim, 16, stride=16)
        x = g.op("Transpose", [g.reshape(x, [1, dim, 4096])], perm=[0, 2, 1])
        x = g.op("Add", [x, g.w((1, 4096, dim), 0.02)])
        for i in range(depth):
            x = g.vit_block(x, 64, 64, dim, heads, 0 if i in glob else window)
        x = g.neck(x, dim)
    elif size == "mobilesam":
        # TinyViT-5M (MobileSAM): stem 3->32->64 (two stride-2 convs) to 256x256
        x = g.gelu(g.conv(x, 3, 32, 3, stride=2, pad=1))
        x = g.conv(x, 32, 64, 3, stride=2, pad=1)
        for _ in range(2):  # MBConv x2, expand 4
            y = g.gelu(g.conv(x, 64, 256, 1))
            y = g.gelu(g.conv(y, 256, 256, 3, pad=1, groups=256))
            x = g.gelu(g.op("Add", [x, g.conv(y, 256, 64, 1)]))
        side, dim = 256, 64
        for (out, depth, heads, window, stride) in ((128, 2, 4, 7, 2), (160, 6, 5, 14, 2), (320, 2, 10, 7, 1)):
            # patch merging: 1x1 up, depthwise 3x3 (stride), 1x1
            y = g.gelu(g.conv(x, dim, out, 1))
            y = g.gelu(g.conv(y, out, out, 3, stride=stride, pad=1, groups=out))
            x = g.conv(y, out, out, 1)
            side //= stride
            dim = out
            t = g.op("Transpose", [g.reshape(x, [1, dim, side * side])], perm=[0, 2, 1])
            for _ in range(depth):
                t = g.vit_block(t, side, side, dim, heads, window)
                # TinyViT's local 3x3 depthwise conv between attention and MLP (folded after)
                img = g.op("Transpose", [g.reshape(t, [1, side, side, dim])], perm=[0, 3, 1, 2])
                img = g.conv(img, dim, dim, 3, pad=1, groups=dim)
                t = g.op("Transpose", [g.reshape(img, [1, dim, side * side])], perm=[0, 2, 1])
            x = g.op("Transpose", [g.reshape(t, [1, side, side, dim])], perm=[0, 3, 1, 2])
        t = g.op("Transpose", [g.reshape(x, [1, dim, 4096])], perm=[0, 2, 1])
        x = g.neck(t, dim)
    else:
        raise SystemExit(f"unknown size {size}")
    out = g.op("Identity", [x], p="image_embeddings")
    g.nodes[-1].output[0] = "image_embeddings"
    graph = helper.make_graph(
        g.nodes, "encoder",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 1024, 1024])],
        [helper.make_tensor_value_info("image_embeddings", TensorProto.FLOAT, [1, 256, 64, 64])],
        g.inits)
    del out
    return graph


def decoder(size, seed, fixed_batch=False, depth=None):
    g = G(seed + 1)
    D = 256
    d0, ds, up1, up2, mlp = (1, 8, 16, 8, 256) if size == "tiny" else (2, 2, 64, 32, 2048)
    depth = depth or d0
    heads = 8
    # prompt encoder: random Fourier features of the points
    # parameters carry the names torch.onnx.export keeps for SAM's modules (SamOnnxModel)
    PE, MD = "model.prompt_encoder", "mask_decoder"
    gauss = g.const(g.rng.normal(size=(2, D // 2)).astype(np.float32), "pe_gauss",
                    f"{PE}.pe_layer.positional_encoding_gaussian_matrix")
    c = g.op("Div", [g.op("Add", ["point_coords", g.f32(0.5)]), g.f32(1024.0)])
    c = g.op("Sub", [g.op("Mul", [c, g.f32(2.0)]), g.f32(1.0)])
    c = g.op("Mul", [g.op("MatMul", [c, gauss]), g.f32(2 * math.pi)])
    pe = g.op("Concat", [g.op("Sin", [c]), g.op("Cos", [c])], axis=-1)  # [B,N,256]
    lab = g.op("Unsqueeze", ["point_labels", g.i64([-1])])

    def is_label(v):
        return g.op("Cast", [g.op("Equal", [lab, g.f32(v)])], to=TensorProto.FLOAT)

    pad = is_label(-1.0)
    sparse = g.op("Mul", [pe, g.op("Sub", [g.f32(1.0), pad])])
    for v, nm in ((-1.0, "not_a_point_embed"), (0.0, "point_embeddings.0"),
                  (1.0, "point_embeddings.1")):
        emb = g.w((D,), 1.0, f"{PE}.{nm}.weight")
        sparse = g.op("Add", [sparse, g.op("Mul", [is_label(v), emb])])
    # dense prompt: mask_input (downscaling convs) or the no-mask embedding
    m = g.gelu(g.conv("mask_input", 1, 4, 2, stride=2))
    m = g.gelu(g.conv(m, 4, 16, 2, stride=2))
    m = g.conv(m, 16, D, 1)
    has = g.reshape("has_mask_input", [1, 1, 1, 1])
    no_mask = g.w((1, D, 1, 1), 1.0)
    dense = g.op("Add", [g.op("Mul", [m, has]), g.op("Mul", [no_mask, g.op("Sub", [g.f32(1.0), has])])])
    # the image positional encoding: the same Fourier features on the 64x64 grid (a constant)
    gm = numpy_helper.to_array(next(i for i in g.inits if i.name == gauss))
    yy, xx = np.meshgrid((np.arange(64) + 0.5) / 64, (np.arange(64) + 0.5) / 64, indexing="ij")
    grid = np.stack([xx, yy], -1) * 2 - 1
    f = 2 * np.pi * grid @ gm
    image_pe = np.concatenate([np.sin(f), np.cos(f)], -1).reshape(1, 4096, D).astype(np.float32)
    key_pe = g.const(image_pe, "image_pe")
    src = g.op("Add", ["image_embeddings", dense])
    keys = g.op("Transpose", [g.reshape(src, [1, D, 4096])], perm=[0, 2, 1])  # [1,4096,256]
    # tokens: iou token, 4 mask tokens, the points
    out_tokens = g.w((1, 5, D), 1.0)
    bshape = g.op("Shape", ["point_coords"], start=0, end=1)
    out_tokens = g.op("Expand", [out_tokens, g.op("Concat", [bshape, g.i64([5, D])], axis=0)])
    tokens = g.op("Concat", [out_tokens, sparse], axis=1)  # [B,5+N,256]
    queries, qpe = tokens, tokens
    for layer in range(depth):
        L = f"{MD}.transformer.layers.{layer}"
        if layer == 0:
            queries = g.attention(queries, queries, queries, D, heads, path=f"{L}.self_attn")
        else:
            q = g.op("Add", [queries, qpe])
            queries = g.op("Add", [queries, g.attention(q, q, queries, D, heads,
                                                        path=f"{L}.self_attn")])
        queries = g.layernorm_op(queries, D, f"{L}.norm1")
        q = g.op("Add", [queries, qpe])
        k = g.op("Add", [keys, key_pe])
        queries = g.layernorm_op(g.op("Add", [queries, g.attention(
            q, k, keys, D, heads, D // ds, path=f"{L}.cross_attn_token_to_image")]), D, f"{L}.norm2")
        hid = g.op("Relu", [g.linear(queries, D, mlp, path=f"{L}.mlp.lin1")])
        queries = g.layernorm_op(g.op("Add", [queries, g.linear(hid, mlp, D, path=f"{L}.mlp.lin2")]),
                                 D, f"{L}.norm3")
        q = g.op("Add", [queries, qpe])
        k = g.op("Add", [keys, key_pe])
        keys = g.layernorm_op(g.op("Add", [keys, g.attention(
            k, q, queries, D, heads, D // ds, path=f"{L}.cross_attn_image_to_token")]), D, f"{L}.norm4")
    q = g.op("Add", [queries, qpe])
    k = g.op("Add", [keys, key_pe])
    queries = g.layernorm_op(g.op("Add", [queries, g.attention(
        q, k, keys, D, heads, D // ds, path=f"{MD}.transformer.final_attn_token_to_image")]),
        D, f"{MD}.transformer.norm_final_attn")
    # keys may still be [1,4096,256] when nothing made them per-prompt: expand to B
    keys = g.op("Expand", [keys, g.op("Concat", [bshape, g.i64([4096, D])], axis=0)])
    img = g.reshape(g.op("Transpose", [keys], perm=[0, 2, 1]), [-1, D, 64, 64])
    up = g.gelu(g.layernorm(g.conv_t(img, D, up1, f"{MD}.output_upscaling.0"), up1, axis=1,
                            path=f"{MD}.output_upscaling.1"))
    up = g.gelu(g.conv_t(up, up1, up2, f"{MD}.output_upscaling.3"))  # [B,up2,256,256]
    up = g.reshape(up, [0, up2, 65536])
    mask_tok = g.op("Slice", [queries, g.i64([1]), g.i64([5]), g.i64([1])])  # [B,4,256]
    hyper = []
    for i in range(4):
        t = g.op("Slice", [mask_tok, g.i64([i]), g.i64([i + 1]), g.i64([1])])
        H = f"{MD}.output_hypernetworks_mlps.{i}.layers"
        t = g.op("Relu", [g.linear(t, D, D, path=f"{H}.0")])
        t = g.op("Relu", [g.linear(t, D, D, path=f"{H}.1")])
        hyper.append(g.linear(t, D, up2, gain=16.0, path=f"{H}.2"))
    hyper = g.op("Concat", hyper, axis=1)  # [B,4,up2]
    low = g.reshape(g.op("MatMul", [hyper, up]), [0, 4, 256, 256])
    iou_tok = g.op("Slice", [queries, g.i64([0]), g.i64([1]), g.i64([1])])
    I = f"{MD}.iou_prediction_head.layers"
    t = g.op("Relu", [g.linear(iou_tok, D, D, path=f"{I}.0")])
    t = g.op("Relu", [g.linear(t, D, D, path=f"{I}.1")])
    iou = g.reshape(g.linear(t, D, 4, gain=0.08, bias_value=np.full(4, 0.88, np.float32),
                             path=f"{I}.2"), [-1, 4])
    # SAM's export post-processing: bilinear to 1024, crop to the resized size, bilinear to orig
    big = g.op("Resize", [low, "", "", g.op("Concat", [g.op("Shape", [low], start=0, end=2),
                                                       g.i64([1024, 1024])], axis=0)],
               mode="linear", coordinate_transformation_mode="half_pixel")
    orig = "orig_im_size"
    scale = g.op("Div", [g.f32(1024.0), g.op("ReduceMax", [orig], keepdims=1)])
    pre = g.op("Cast", [g.op("Floor", [g.op("Add", [g.op("Mul", [orig, scale]), g.f32(0.5)])])],
               to=TensorProto.INT64)
    big = g.op("Slice", [big, g.i64([0, 0]), pre, g.i64([2, 3])])
    size = g.op("Concat", [g.op("Shape", [low], start=0, end=2),
                           g.op("Cast", [orig], to=TensorProto.INT64)], axis=0)
    masks = g.op("Resize", [big, "", "", size], mode="linear",
                 coordinate_transformation_mode="half_pixel")
    for src_name, dst in ((masks, "masks"), (iou, "iou_predictions"), (low, "low_res_masks")):
        g.nodes.append(helper.make_node("Identity", [src_name], [dst]))
    # SAM's own export traces one prompt per call (dynamic `num_points` only): --fixed-batch
    batch = 1 if fixed_batch else "batch"
    inputs = [
        helper.make_tensor_value_info("image_embeddings", TensorProto.FLOAT, [1, 256, 64, 64]),
        helper.make_tensor_value_info("point_coords", TensorProto.FLOAT, [batch, "num_points", 2]),
        helper.make_tensor_value_info("point_labels", TensorProto.FLOAT, [batch, "num_points"]),
        helper.make_tensor_value_info("mask_input", TensorProto.FLOAT, [1, 1, 256, 256]),
        helper.make_tensor_value_info("has_mask_input", TensorProto.FLOAT, [1]),
        helper.make_tensor_value_info("orig_im_size", TensorProto.FLOAT, [2]),
    ]
    outputs = [
        helper.make_tensor_value_info("masks", TensorProto.FLOAT, ["batch", 4, "h", "w"]),
        helper.make_tensor_value_info("iou_predictions", TensorProto.FLOAT, ["batch", 4]),
        helper.make_tensor_value_info("low_res_masks", TensorProto.FLOAT, ["batch", 4, 256, 256]),
    ]
    return helper.make_graph(g.nodes, "decoder", inputs, outputs, g.inits)


# ---------------------------------------------------------------------------------------------
# CLIP (gs4city features): image encoder, text encoder, BPE files

CLIP_SIZES = {
    # image: patch, width, layers, heads; text: width, layers, heads, vocabulary; embedding
    "tiny": dict(patch=32, width=48, layers=2, heads=2, twidth=32, tlayers=1, theads=2,
                 vocab=None, embed=24),
    # OpenAI CLIP ViT-B/32: 87.8 M image + 63.2 M text parameters (with the embeddings)
    "vit_b32": dict(patch=32, width=768, layers=12, heads=12, twidth=512, tlayers=12, theads=8,
                    vocab=49408, embed=512),
}
CONTEXT = 77

# The training text of the test BPE (a few hundred merges): city words, the class prompts,
# contractions, digits, punctuation and non-ASCII letters.
CORPUS = """
a wall of a building. a facade of a building. a roof. a window of a building. a door.
the ground surface of a building. a balcony of a building. a tree. a person. a car. a road.
water. the sky. a building. the windows of the buildings; the doors of the houses! roofs,
chimneys, dormers and balconies. it's a tall building, isn't it? we're near the street's end.
they've parked 2 cars and 13 bicycles in 2024. the café on the straße has a green façade.
street lamps, traffic signs, poles, trees, bushes and people walking on the sidewalk.
"""


def clip_bpe(out, merges_wanted=300):
    """Trains a byte-level BPE with CLIP's conventions (`</w>` word ends) on CORPUS with the
    `tokenizers` library and writes vocab.json + merges.txt in CLIP's layout: the 256 byte
    characters, the same with `</w>`, one token per merge, <|startoftext|>, <|endoftext|>."""
    import tempfile
    from tokenizers import Regex, Tokenizer, models, normalizers, pre_tokenizers, trainers
    byte_level = pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)
    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet(), key=ord)
    tok = Tokenizer(models.BPE(end_of_word_suffix="</w>"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Sequence([
        pre_tokenizers.Split(Regex(r"""'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""),
                             behavior="removed", invert=True),
        byte_level])
    trainer = trainers.BpeTrainer(vocab_size=2 * len(alphabet) + merges_wanted, show_progress=False,
                                  initial_alphabet=alphabet, end_of_word_suffix="</w>")
    tok.train_from_iterator([CORPUS] * 3, trainer)
    with tempfile.TemporaryDirectory() as d:
        tok.model.save(d)
        with open(os.path.join(d, "merges.txt"), encoding="utf-8") as f:
            merges = [tuple(l.rstrip("\n").split(" ")) for l in f if l.strip() and not l.startswith("#version")]
    tokens = alphabet + [c + "</w>" for c in alphabet]
    seen = set(tokens)
    for a, b in merges:
        if a + b not in seen:
            seen.add(a + b)
            tokens.append(a + b)
    tokens += ["<|startoftext|>", "<|endoftext|>"]
    with open(os.path.join(out, "vocab.json"), "w", encoding="utf-8") as f:
        json.dump({t: i for i, t in enumerate(tokens)}, f, ensure_ascii=False)
    with open(os.path.join(out, "merges.txt"), "w", encoding="utf-8") as f:
        f.write("#version: 0.2\n")
        f.writelines(f"{a} {b}\n" for a, b in merges)
    return len(tokens)


def clip_image(size, seed):
    """CLIP's ViT: patch conv, class token, positions, ln_pre, pre-norm blocks, ln_post on the
    class token, projection: pixel_values [B,3,224,224] -> image_embeds [B,E]."""
    c = CLIP_SIZES[size]
    g = G(seed + 2)
    W, P, E = c["width"], c["patch"], c["embed"]
    n = 224 // P
    x = g.conv("pixel_values", 3, W, P, stride=P)
    x = g.op("Transpose", [g.reshape(x, [0, W, n * n])], perm=[0, 2, 1])  # [B, n*n, W]
    bshape = g.op("Shape", ["pixel_values"], start=0, end=1)
    cls = g.op("Expand", [g.w((1, 1, W), 1.0), g.op("Concat", [bshape, g.i64([1, W])], axis=0)])
    x = g.op("Concat", [cls, x], axis=1)
    x = g.op("Add", [x, g.w((1, n * n + 1, W), 0.2)])
    x = g.layernorm(x, W)
    for _ in range(c["layers"]):
        x = g.vit_block(x, 0, 0, W, c["heads"], 0)
    t = g.layernorm(g.op("Slice", [x, g.i64([0]), g.i64([1]), g.i64([1])]), W)
    t = g.reshape(g.op("MatMul", [t, g.w((W, E), 1.0 / math.sqrt(W))]), [-1, E])
    g.nodes.append(helper.make_node("Identity", [t], ["image_embeds"]))
    return helper.make_graph(
        g.nodes, "clip_image",
        [helper.make_tensor_value_info("pixel_values", TensorProto.FLOAT, ["batch", 3, 224, 224])],
        [helper.make_tensor_value_info("image_embeds", TensorProto.FLOAT, ["batch", E])],
        g.inits)


def clip_text(size, seed, vocab):
    """CLIP's text transformer: token + position embeddings, causal pre-norm blocks, ln_final,
    the state at <|endoftext|> (argmax of the ids), projection: input_ids [B,77] int64 ->
    text_embeds [B,E]."""
    c = CLIP_SIZES[size]
    g = G(seed + 3)
    W, E = c["twidth"], c["embed"]
    x = g.op("Gather", [g.w((vocab, W), 1.0), "input_ids"], axis=0)  # [B,77,W]
    x = g.op("Add", [x, g.w((1, CONTEXT, W), 0.1)])
    causal = g.const(np.triu(np.full((CONTEXT, CONTEXT), -1e9, np.float32), 1), "causal")
    for _ in range(c["tlayers"]):
        x = g.vit_block(x, 0, 0, W, c["theads"], 0, mask=causal)
    x = g.layernorm(x, W)
    eot = g.op("ArgMax", ["input_ids"], axis=1, keepdims=1)  # [B,1]
    pos = g.const(np.arange(CONTEXT, dtype=np.int64)[None, :], "positions")
    onehot = g.op("Cast", [g.op("Equal", [pos, eot])], to=TensorProto.FLOAT)  # [B,77]
    pooled = g.op("MatMul", [g.op("Unsqueeze", [onehot, g.i64([1])]), x])  # [B,1,W]
    t = g.reshape(g.op("MatMul", [pooled, g.w((W, E), 1.0 / math.sqrt(W))]), [-1, E])
    g.nodes.append(helper.make_node("Identity", [t], ["text_embeds"]))
    return helper.make_graph(
        g.nodes, "clip_text",
        [helper.make_tensor_value_info("input_ids", TensorProto.INT64, ["batch", CONTEXT])],
        [helper.make_tensor_value_info("text_embeds", TensorProto.FLOAT, ["batch", E])],
        g.inits)


def save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                              producer_name="gs4city make_test_models.py (random weights)")
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", choices=["tiny", "mobilesam", "vit_b"])
    ap.add_argument("--clip", choices=sorted(CLIP_SIZES))
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fixed-batch", action="store_true",
                    help="decoder inputs with batch 1, as SAM's own export (one prompt per call)")
    ap.add_argument("--decoder-depth", type=int,
                    help="two-way transformer layers (default: 1 tiny, 2 as SAM otherwise)")
    ap.add_argument("--decoder-only", action="store_true",
                    help="write decoder.onnx alone (no encoder, no model.json): the decoder checks")
    a = ap.parse_args()
    if (a.size is None) == (a.clip is None):
        ap.error("give one of --size (SAM family) and --clip")
    os.makedirs(a.out, exist_ok=True)
    if a.clip:
        n = clip_bpe(a.out)
        save(clip_image(a.clip, a.seed), os.path.join(a.out, "clip_image.onnx"))
        save(clip_text(a.clip, a.seed, CLIP_SIZES[a.clip]["vocab"] or n), os.path.join(a.out, "clip_text.onnx"))
        return
    save(decoder(a.size, a.seed, a.fixed_batch, a.decoder_depth), os.path.join(a.out, "decoder.onnx"))
    if a.decoder_only:
        return
    save(encoder(a.size, a.seed), os.path.join(a.out, "encoder.onnx"))
    family = {"tiny": "test", "mobilesam": "mobile_sam", "vit_b": "sam"}[a.size]
    with open(os.path.join(a.out, "model.json"), "w") as f:
        json.dump({"family": family, "size": a.size, "generated": True,
                   "note": "RANDOM weights written by scripts/make_test_models.py"}, f, indent=1)


if __name__ == "__main__":
    main()
