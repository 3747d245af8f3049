#!/usr/bin/env python3
"""What a deforming phantom's wave costs a rigid registration (docs/results/nonrigid.md).

For every frame that has a true surface (`gt_surface_NNNNNN.ply`, written by
`capsule-slam synth --deform MM --surface-every N`), the wall points the true camera sees
(inside the image, 5-80 mm deep, facing the camera; occlusion ignored) are fitted rigidly
(Kabsch) to the same material points on the rest shape (`gt_surface.ply`, one material grid).
A tracker that registers the live wall rigidly against a rest-shape map moves its camera by
that fit: the camera offset it implies is printed as RMS and max over the frames, in mm.

Usage: python3 common_mode.py SEQUENCE_DIR...   (needs numpy and scipy)
"""
import os
import re
import sys
import tomllib

import numpy as np
from scipy.spatial.transform import Rotation

TYPES = {"float": "<f4", "double": "<f8", "uchar": "u1", "uint": "<u4", "int": "<i4"}


def read_ply(path):
    """The vertices of a binary little-endian PLY as a structured array."""
    with open(path, "rb") as f:
        props, n = [], 0
        while (line := f.readline().decode().strip()) != "end_header":
            if line.startswith("element vertex"):
                n = int(line.split()[2])
            elif line.startswith("property"):
                _, kind, name = line.split()
                props.append((name, TYPES[kind]))
        return np.frombuffer(f.read(), dtype=np.dtype(props), count=n)


def xyz(v, prefix=""):
    return np.stack([v[prefix + "x"], v[prefix + "y"], v[prefix + "z"]], 1).astype(float)


def kabsch(a, b):
    """R, t minimising |R a + t - b|."""
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ d @ vt
    return r, mb - r @ ma


def offsets(seq):
    cam = tomllib.load(open(os.path.join(seq, "camera.toml"), "rb"))
    gt = np.loadtxt(os.path.join(seq, "groundtruth.txt"))
    rest = xyz(read_ply(os.path.join(seq, "gt_surface.ply")))
    out = []
    for name in sorted(os.listdir(seq)):
        m = re.fullmatch(r"gt_surface_(\d+)\.ply", name)
        if not m:
            continue
        v = read_ply(os.path.join(seq, name))
        now, normals = xyz(v), xyz(v, "n")
        t, r_wc = gt[int(m.group(1)), 1:4], Rotation.from_quat(gt[int(m.group(1)), 4:8]).as_matrix()
        p, n = (now - t) @ r_wc, normals @ r_wc
        u = cam["fx"] * p[:, 0] / p[:, 2] + cam["cx"]
        w = cam["fy"] * p[:, 1] / p[:, 2] + cam["cy"]
        seen = (p[:, 2] > 0.005) & (p[:, 2] < 0.08) & (u >= 0) & (u < cam["width"]) & (w >= 0) & (w < cam["height"]) & ((n * p).sum(1) < 0)
        r, tr = kabsch(rest[seen], now[seen])
        out.append(np.linalg.norm(r.T @ (t - tr) - t))
    return np.array(out)


if __name__ == "__main__":
    for seq in sys.argv[1:]:
        o = offsets(seq)
        print(f"{seq}: {len(o)} frames, camera offset RMS {np.sqrt(np.mean(o**2)) * 1e3:.3f} mm, max {o.max() * 1e3:.3f} mm")
