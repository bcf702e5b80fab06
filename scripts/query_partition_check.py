#!/usr/bin/env python3
"""Independent check that `gs4city query --export` partitions the input PLY exactly: extract.ply
holds the input records of the selected Gaussians (labels of selection.json in the mode's
gaussians.npy), remove.ply the others, byte for byte, in input order, each record followed by the
int32 columns label, class, feature_id, surface_id, part_id; label and class equal gaussians.npy
(float32 input properties, NumPy only).

    python3 scripts/query_partition_check.py RUN_DIR QUERY_DIR [--scene SCENE_DIR]
"""
import json, sys, numpy as np
COLS = ['label', 'class', 'feature_id', 'surface_id', 'part_id']
def ply(path):
    b = open(path, 'rb').read()
    end = b.index(b'end_header\n') + 11
    head = b[:end].decode().splitlines()
    n = int([l for l in head if l.startswith('element vertex')][0].split()[2])
    props = [(l.split()[2], l.split()[1]) for l in head if l.startswith('property')]
    assert all(t in ('float', 'int') for _, t in props)
    rec = np.frombuffer(b[end:end + n * 4 * len(props)], dtype=np.uint8).reshape(n, 4 * len(props))
    return [p for p, _ in props], rec
run, q = sys.argv[1], sys.argv[2]
scene = sys.argv[4] if len(sys.argv) > 4 and sys.argv[3] == '--scene' else json.load(open(run + '/run.json'))['scene']
p0, src = ply(scene + '/point_cloud.ply')
pa, a = ply(q + '/extract.ply'); pb, b = ply(q + '/remove.ply')
assert pa == pb == p0 + COLS, (pa, p0)
w = 4 * len(p0)
summary = json.load(open(q + '/summary.json'))
mode = 'train' if summary['mode'] == 'learned' else 'lift'
table = np.load(run + '/' + mode + '/gaussians.npy')
sel = np.isin(table[:, 0], json.load(open(q + '/selection.json'))['labels'])
print('input', len(src), 'extract', len(a), 'remove', len(b), 'selected', sel.sum())
print('extract == input[selected]:', np.array_equal(a[:, :w], src[sel]))
print('remove == input[~selected]:', np.array_equal(b[:, :w], src[~sel]))
cols = lambda r: np.ascontiguousarray(r[:, w:w + 8]).view('<i4')
print('label, class == gaussians.npy:', np.array_equal(cols(a), table[sel]) and np.array_equal(cols(b), table[~sel]))
