#!/usr/bin/env python3
"""Where a run's live surface error comes from, by how long ago each surfel was seen
(docs/results/nonrigid.md).

The live surface error (`capsule-slam eval`/`run`) takes the surfels of `map.ply` seen in the
last WINDOW frames, moves them by the trajectory's SE(3) alignment to the truth (fitted to all
poses, or to the last ALIGN poses with `--align ALIGN`) and measures their point-to-plane
distance to the true wall at the last frame (`gt_surface_NNNNNN.ply`, nearest true point and
its normal). This script splits that error by the surfel's age (last frame - its `t`) and, for
comparison, measures each surfel against the true wall at the written frame nearest the one
that last saw it (`--surface-every N` sequences): what the surfel would score had the wall not
moved since.

Usage: python3 live_by_age.py RUN_DIR SEQUENCE_DIR [--align 30] [--window 30]
(needs numpy and scipy)
"""
import argparse
import os

import numpy as np
from scipy.spatial import cKDTree

from common_mode import kabsch, read_ply, xyz  # the same folder

BINS = [(0, 0), (1, 5), (6, 10), (11, 20), (21, 30)]


def plane_distance(points, surface):
    """Point-to-plane distance of each point to its nearest point of a true surface."""
    g, gn = xyz(surface), xyz(surface, "n")
    _, i = cKDTree(g).query(points)
    return np.abs(((points - g[i]) * gn[i]).sum(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("sequence")
    ap.add_argument("--align", type=int, default=0, help="fit the alignment to the last ALIGN poses (0: all)")
    ap.add_argument("--window", type=int, default=30, help="surfels seen in the last WINDOW frames")
    a = ap.parse_args()
    est = np.loadtxt(os.path.join(a.run, "trajectory.txt"))[:, 1:4]
    gt = np.loadtxt(os.path.join(a.sequence, "groundtruth.txt"))[:, 1:4]
    last = len(gt) - 1
    r, t = kabsch(est[-a.align:], gt[-a.align:]) if a.align else kabsch(est, gt)
    m = read_ply(os.path.join(a.run, "map.ply"))
    sel = m["t"].astype(int) >= last - a.window
    p = xyz(m)[sel] @ r.T + t
    seen = m["t"][sel].astype(int)
    age = last - seen
    now = plane_distance(p, read_ply(os.path.join(a.sequence, f"gt_surface_{last:06d}.ply")))
    # Each surfel against the written true surface nearest the frame that last saw it.
    written = sorted(int(f[11:17]) for f in os.listdir(a.sequence) if f.startswith("gt_surface_0"))
    nearest = np.array([min(written, key=lambda w: abs(w - s)) for s in seen])
    then = np.full(len(p), np.nan)
    for w in np.unique(nearest):
        s = nearest == w
        then[s] = plane_distance(p[s], read_ply(os.path.join(a.sequence, f"gt_surface_{w:06d}.ply")))
    rms = lambda e: np.sqrt(np.mean(e**2)) * 1e3
    print(f"{len(p)} surfels, RMSE {rms(now):.3f} mm, median {np.median(now) * 1e3:.3f} mm")
    print("age (frames)  surfels  RMSE now  share of SSE  RMSE against the wall when last seen")
    for lo, hi in BINS:
        s = (age >= lo) & (age <= hi)
        if s.any():
            print(f"{lo:3d}-{hi:<3d}      {s.sum():8d}  {rms(now[s]):7.3f}  {np.sum(now[s]**2) / np.sum(now**2):11.2f}  {rms(then[s]):7.3f}")


if __name__ == "__main__":
    main()
