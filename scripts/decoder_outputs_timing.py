#!/usr/bin/env python3
"""CPU seconds per SAM decoder call (64 prompts, 1 thread, image 165x124) with all outputs vs
only iou_predictions + low_res_masks (BENCHMARKS.md, "segment", low-resolution masks only).

Usage: python3 scripts/decoder_outputs_timing.py MODEL_DIR   (from make_test_models.py)
"""
import time, numpy as np, onnxruntime as ort, sys
d = sys.argv[1]
so = ort.SessionOptions(); so.intra_op_num_threads = 1
s = ort.InferenceSession(d + "/decoder.onnx", so)
b = 64
rng = np.random.default_rng(0)
feeds = {"image_embeddings": rng.normal(size=(1,256,64,64)).astype(np.float32),
         "point_coords": (rng.random((b,2,2))*1024).astype(np.float32),
         "point_labels": np.tile(np.array([[1,-1]], np.float32), (b,1)),
         "mask_input": np.zeros((1,1,256,256), np.float32), "has_mask_input": np.zeros(1, np.float32),
         "orig_im_size": np.array([124,165], np.float32)}
for names in (None, ["iou_predictions", "low_res_masks"], None, ["iou_predictions", "low_res_masks"]):
    s.run(names, feeds)
    c = time.process_time(); t = time.time()
    for _ in range(3): s.run(names, feeds)
    print(names or "all outputs", f"CPU s per 64 prompts {(time.process_time()-c)/3:.3f} wall {(time.time()-t)/3:.3f}")
