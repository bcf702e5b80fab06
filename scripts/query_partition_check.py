#!/usr/bin/env python3
"""Independent check that `gs4city query --export` partitions the input PLY exactly: extract.ply
holds the input records of the selected Gaussians (labels of selection.json in R/lift/gaussians.npy),
remove.ply the others, byte for byte, in input order (float32 properties, NumPy only).

    python3 scripts/query_partition_check.py RUN_DIR QUERY_DIR
"""
import json, sys, numpy as np
def ply(path):
    b = open(path, 'rb').read()
    end = b.index(b'end_header\n') + 11
    head = b[:end].decode().splitlines()
    n = int([l for l in head if l.startswith('element vertex')][0].split()[2])
    props = [l.split()[2] for l in head if l.startswith('property')]
    assert all(l.split()[1] == 'float' for l in head if l.startswith('property'))
    rec = np.frombuffer(b[end:end + n * 4 * len(props)], dtype=np.uint8).reshape(n, 4 * len(props))
    return props, rec
run, q = sys.argv[1], sys.argv[2]
scene = json.load(open(run + '/run.json'))['scene']
p0, src = ply(scene + '/point_cloud.ply')
pa, a = ply(q + '/extract.ply'); pb, b = ply(q + '/remove.ply')
assert p0 == pa == pb
lab = np.load(run + '/lift/gaussians.npy')[:, 0]
sel = np.isin(lab, json.load(open(q + '/selection.json'))['labels'])
print('input', len(src), 'extract', len(a), 'remove', len(b), 'selected', sel.sum())
print('extract == input[selected]:', np.array_equal(a, src[sel]))
print('remove == input[~selected]:', np.array_equal(b, src[~sel]))
