#!/usr/bin/env python3
"""What a deforming phantom's wave costs a rigid registration (docs/results/nonrigid.md).

For every frame that has a true surface (`gt_surface_NNNNNN.ply`, written by
`capsule-slam synth --deform MM --surface-every N`), the wall points the true camera sees
(inside the image, 5-80 mm deep, facing the camera; occlusion ignored) are fitted rigidly
(Kabsch) to the same material points on the rest shape (`gt_surface.ply`, one material grid).
A tracker that registers the live wall rigidly against a rest-shape map moves its camera by
that fit: the camera offset it implies is printed as RMS and max over the frames, in mm.

With `--per-frame`, the same points are fitted between consecutive written surfaces instead
(frame a's visible material points at frame a and at frame b, in camera a's frame): the wall's
common motion in view, inverted and divided by b - a, is the extra motion per frame a tracker
that registers the camera to the visible wall alone would give the camera. Its mean over the
run (rotation about the camera's x, y, z in degrees; translation in mm) is the bias no
registration to the visible wall can see.

Usage: python3 common_mode.py [--per-frame] SEQUENCE_DIR...   (needs numpy and scipy)
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


def surfaces(seq):
    """The written true surfaces: (frame, file name), in frame order."""
    found = [(int(m.group(1)), name) for name in os.listdir(seq) if (m := re.fullmatch(r"gt_surface_(\d+)\.ply", name))]
    return sorted(found)


def visible(seq, frame, v):
    """Frame `frame`'s true camera (R_wc, t) and the mask of the points of `v` it sees."""
    cam = tomllib.load(open(os.path.join(seq, "camera.toml"), "rb"))
    gt = np.loadtxt(os.path.join(seq, "groundtruth.txt"))
    t, r_wc = gt[frame, 1:4], Rotation.from_quat(gt[frame, 4:8]).as_matrix()
    p, n = (xyz(v) - t) @ r_wc, xyz(v, "n") @ r_wc
    u = cam["fx"] * p[:, 0] / p[:, 2] + cam["cx"]
    w = cam["fy"] * p[:, 1] / p[:, 2] + cam["cy"]
    seen = (p[:, 2] > 0.005) & (p[:, 2] < 0.08) & (u >= 0) & (u < cam["width"]) & (w >= 0) & (w < cam["height"]) & ((n * p).sum(1) < 0)
    return r_wc, t, seen


def offsets(seq):
    rest = xyz(read_ply(os.path.join(seq, "gt_surface.ply")))
    out = []
    for frame, name in surfaces(seq):
        v = read_ply(os.path.join(seq, name))
        _, t, seen = visible(seq, frame, v)
        r, tr = kabsch(rest[seen], xyz(v)[seen])
        out.append(np.linalg.norm(r.T @ (t - tr) - t))
    return np.array(out)


def per_frame(seq):
    """The camera's apparent extra motion per frame between consecutive written surfaces, in
    the earlier camera's frame: rotation vectors (deg) and translations (mm)."""
    rots, shifts = [], []
    found = surfaces(seq)
    for (a, name_a), (b, name_b) in zip(found, found[1:]):
        va, vb = read_ply(os.path.join(seq, name_a)), read_ply(os.path.join(seq, name_b))
        r_wc, t, seen = visible(seq, a, va)
        pa, pb = (xyz(va)[seen] - t) @ r_wc, (xyz(vb)[seen] - t) @ r_wc
        r, tr = kabsch(pa, pb)
        # The wall moved by (r, tr) in camera a's frame; the camera, registered to it, by the inverse.
        rots.append(np.degrees(Rotation.from_matrix(r.T).as_rotvec()) / (b - a))
        shifts.append(-r.T @ tr * 1e3 / (b - a))
    return np.array(rots), np.array(shifts)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--per-frame"]
    for seq in args:
        if "--per-frame" in sys.argv:
            rots, shifts = per_frame(seq)
            print(f"{seq}: the wall's common motion seen as the camera's, per frame: rotation mean {rots.mean(0).round(4)} deg "
                  f"(RMS {np.sqrt((rots**2).mean(0)).round(4)}), translation mean {shifts.mean(0).round(4)} mm")
        else:
            o = offsets(seq)
            print(f"{seq}: {len(o)} frames, camera offset RMS {np.sqrt(np.mean(o**2)) * 1e3:.3f} mm, max {o.max() * 1e3:.3f} mm")
