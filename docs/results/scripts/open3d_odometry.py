#!/usr/bin/env python3
"""Open3D's rigid RGB-D odometry, frame to frame, on a capsule-slam sequence (the peer of
issue 16's table: "Open3D 0.20 rigid RGB-D odometry, frame to frame").

Reads a sequence folder as `capsule-slam run` does (`camera.toml`, `rgb.txt`, `depth.txt`,
16-bit depth PNGs in units of 1/depth_scale m), registers every frame to the previous one with
`o3d.pipelines.odometry.compute_rgbd_odometry` (hybrid photometric + geometric term, Steinbrücker
2011 / Park 2017), chains the motions from the identity and writes a TUM trajectory. A frame
whose odometry fails keeps the previous frame's motion (constant velocity) and is counted as lost.
Evaluate it like any estimate:

    python3 open3d_odometry.py SEQ OUT.txt [--depth-diff-max M] [--depth-max M]
    capsule-slam eval --gt SEQ/groundtruth.txt --est OUT.txt

`--depth-diff-max` is Open3D's correspondence gate on depth (its default 0.03 m is room scale).
Needs `pip install open3d==0.20.0 numpy`.
"""
import argparse
import os
import sys
import tomllib

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation


def listing(path):
    with open(path) as f:
        return [line.split() for line in f if line.strip() and not line.startswith("#")]


def chain(seq, out, frames, register):
    """Registers every frame to the previous one (`register(current, previous, guess)` gives the
    motion mapping current-frame points into the previous frame, or None), chains the motions
    from the identity and writes the TUM trajectory `out`. A failed registration keeps the
    previous motion (constant velocity) and counts as lost."""
    pose, motion, lost = np.eye(4), np.eye(4), 0
    rows = []
    for k, (t, im) in enumerate(frames):
        if k > 0:
            m = register(im, frames[k - 1][1], motion)
            if m is None:
                lost += 1
            else:
                motion = m
            pose = pose @ motion
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        rows.append(f"{t:.6f} {pose[0, 3]:.9f} {pose[1, 3]:.9f} {pose[2, 3]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    with open(out, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    print(f"{seq}: {len(frames)} frames, {lost} lost (odometry failed), written {out}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("seq")
    ap.add_argument("out")
    ap.add_argument("--depth-diff-max", type=float, default=0.03)
    ap.add_argument("--depth-max", type=float, default=1.0, help="depths beyond this (m) are cut; 1 m suits the phantom, 4 m a room")
    ap.add_argument("--method", choices=["legacy-hybrid", "point-to-plane", "hybrid", "intensity"], default="legacy-hybrid")
    a = ap.parse_args()
    with open(os.path.join(a.seq, "camera.toml"), "rb") as f:
        cam = tomllib.load(f)
    rgb, depth = listing(os.path.join(a.seq, "rgb.txt")), listing(os.path.join(a.seq, "depth.txt"))
    if len(rgb) != len(depth):
        sys.exit(f"{a.seq}: {len(rgb)} colour and {len(depth)} depth frames")
    paths = [(float(t), os.path.join(a.seq, c), os.path.join(a.seq, d)) for (t, c), (_, d) in zip(rgb, depth)]
    (legacy if a.method == "legacy-hybrid" else tensor)(a, cam, paths)


def legacy(a, cam, paths):
    """`compute_rgbd_odometry` with the hybrid term and Open3D's options but the depth gate."""
    intr = o3d.camera.PinholeCameraIntrinsic(cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"])
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_diff_max = a.depth_diff_max
    option.depth_min, option.depth_max = 0.0, a.depth_max
    term = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    frames = [(t, o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.io.read_image(c), o3d.io.read_image(d), depth_scale=cam["depth_scale"], depth_trunc=a.depth_max,
        convert_rgb_to_intensity=True)) for t, c, d in paths]

    def register(cur, prev, guess):
        ok, t_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(cur, prev, intr, guess, term, option)
        return t_prev_cur if ok else None

    chain(a.seq, a.out, frames, register)


def tensor(a, cam, paths):
    """The tensor API's multi-scale odometry (`o3d.t.pipelines.odometry`), point to plane,
    intensity or hybrid, with the depth gate and Huber scales at organ scale."""
    import open3d.core as o3c
    T = o3d.t.pipelines.odometry
    k = o3c.Tensor([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], o3c.float64)
    method = {"point-to-plane": T.Method.PointToPlane, "hybrid": T.Method.Hybrid, "intensity": T.Method.Intensity}[a.method]
    params = T.OdometryLossParams(depth_outlier_trunc=a.depth_diff_max, depth_huber_delta=a.depth_diff_max / 4, intensity_huber_delta=0.1)
    crit = [T.OdometryConvergenceCriteria(20), T.OdometryConvergenceCriteria(10), T.OdometryConvergenceCriteria(5)]
    frames = [(t, o3d.t.geometry.RGBDImage(o3d.t.io.read_image(c).to(o3c.float32), o3d.t.io.read_image(d))) for t, c, d in paths]

    def register(cur, prev, guess):
        try:
            res = T.rgbd_odometry_multi_scale(cur, prev, k, o3c.Tensor(guess), cam["depth_scale"], a.depth_max, crit, method, params)
        except RuntimeError:
            return None
        m = res.transformation.numpy()
        return m if np.all(np.isfinite(m)) and res.fitness > 0 else None

    chain(a.seq, a.out, frames, register)


if __name__ == "__main__":
    main()
