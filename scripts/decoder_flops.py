#!/usr/bin/env python3
"""Multiply-accumulates of one prompt through a SAM-family ONNX decoder (the bound on the decoder's cost per prompt).

    python3 scripts/decoder_flops.py DIR/decoder.onnx

Fixes batch = 1 prompt of 2 points (the point and SAM's padding point), runs ONNX Runtime's
symbolic shape inference, and sums the MACs of every MatMul/Gemm (output elements x inner
dimension), Conv (output elements x kernel volume x input channels per group) and
ConvTranspose (input elements x output channels x kernel area) node. Prints JSON.
"""
import json
import sys

import numpy as np
import onnx
from onnxruntime.tools.symbolic_shape_infer import SymbolicShapeInference


def main():
    m = onnx.load(sys.argv[1])
    for i in m.graph.input:
        dims = i.type.tensor_type.shape.dim
        for d in dims:
            if d.dim_param:
                d.ClearField("dim_param")
                d.dim_value = 1
        if i.name in ("point_coords", "point_labels"):
            dims[0].dim_value = 1
            dims[1].dim_value = 2
    inf = SymbolicShapeInference.infer_shapes(m, auto_merge=True)
    shapes = {}
    for v in list(inf.graph.value_info) + list(inf.graph.input) + list(inf.graph.output):
        shapes[v.name] = [d.dim_value if d.HasField("dim_value") else None for d in v.type.tensor_type.shape.dim]
    for t in inf.graph.initializer:
        shapes[t.name] = list(t.dims)
    tot, unknown = {}, []
    for n in inf.graph.node:
        if n.op_type in ("MatMul", "Gemm"):
            a, o = shapes.get(n.input[0]), shapes.get(n.output[0])
            if not a or not o or None in a or None in o:
                unknown.append(n.name)
                continue
            macs = int(np.prod(o)) * a[-1]
        elif n.op_type == "Conv":
            w, o = shapes[n.input[1]], shapes[n.output[0]]
            macs = int(np.prod(o)) * int(np.prod(w[1:]))
        elif n.op_type == "ConvTranspose":
            w, x = shapes[n.input[1]], shapes[n.input[0]]
            macs = int(np.prod(x)) * int(np.prod(w[1:]))
        else:
            continue
        tot[n.op_type] = tot.get(n.op_type, 0) + macs
    print(json.dumps({"macs_per_prompt": sum(tot.values()), "by_op": tot, "unknown_nodes": unknown}))


if __name__ == "__main__":
    main()
