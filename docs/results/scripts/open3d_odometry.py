#!/usr/bin/env python3
"""Open3D's rigid RGB-D odometry, frame to frame, on a capsule-slam sequence (the peer of
issue 16's table: "Open3D 0.20 rigid RGB-D odometry, frame to frame").

Reads a sequence folder as `capsule-slam run` does (`camera.toml`, `rgb.txt`, `depth.txt`,
16-bit depth PNGs in units of 1/depth_scale m), registers every frame to the previous one with
`o3d.pipelines.odometry.compute_rgbd_odometry` (hybrid photometric + geometric term, Steinbrücker
2011 / Park 2017), chains the motions from the identity and writes a TUM trajectory. A frame
whose odometry fails keeps the previous frame's motion (constant velocity) and is counted as lost.
Evaluate it like any estimate:

    python3 open3d_odometry.py SEQ OUT.txt [--depth-diff-max M]
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


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("seq")
    ap.add_argument("out")
    ap.add_argument("--depth-diff-max", type=float, default=0.03)
    ap.add_argument("--method", choices=["legacy-hybrid", "point-to-plane", "hybrid", "intensity"], default="legacy-hybrid")
    a = ap.parse_args()
    if a.method != "legacy-hybrid":
        return tensor(a)
    with open(os.path.join(a.seq, "camera.toml"), "rb") as f:
        cam = tomllib.load(f)
    intr = o3d.camera.PinholeCameraIntrinsic(cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"])
    rgb, depth = listing(os.path.join(a.seq, "rgb.txt")), listing(os.path.join(a.seq, "depth.txt"))
    if len(rgb) != len(depth):
        sys.exit(f"{a.seq}: {len(rgb)} colour and {len(depth)} depth frames")
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_diff_max = a.depth_diff_max
    option.depth_min, option.depth_max = 0.0, 1.0
    term = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    frames = []
    for (t, c), (_, d) in zip(rgb, depth):
        color = o3d.io.read_image(os.path.join(a.seq, c))
        dep = o3d.io.read_image(os.path.join(a.seq, d))
        frames.append((float(t), o3d.geometry.RGBDImage.create_from_color_and_depth(
            color, dep, depth_scale=cam["depth_scale"], depth_trunc=1.0, convert_rgb_to_intensity=True)))
    pose, motion, lost = np.eye(4), np.eye(4), 0
    rows = []
    for k, (t, im) in enumerate(frames):
        if k > 0:
            ok, t_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(im, frames[k - 1][1], intr, motion, term, option)
            if ok:
                motion = t_prev_cur
            else:
                lost += 1
            pose = pose @ motion
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        rows.append(f"{t:.6f} {pose[0, 3]:.9f} {pose[1, 3]:.9f} {pose[2, 3]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    with open(a.out, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    print(f"{a.seq}: {len(frames)} frames, {lost} lost (odometry failed), written {a.out}")


def tensor(a):
    """The tensor API's multi-scale odometry (`o3d.t.pipelines.odometry`), point to plane,
    intensity or hybrid, with the depth gate and Huber scales at organ scale."""
    import open3d.core as o3c
    T = o3d.t.pipelines.odometry
    with open(os.path.join(a.seq, "camera.toml"), "rb") as f:
        cam = tomllib.load(f)
    k = o3c.Tensor([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], o3c.float64)
    rgb, depth = listing(os.path.join(a.seq, "rgb.txt")), listing(os.path.join(a.seq, "depth.txt"))
    method = {"point-to-plane": T.Method.PointToPlane, "hybrid": T.Method.Hybrid, "intensity": T.Method.Intensity}[a.method]
    params = T.OdometryLossParams(depth_outlier_trunc=a.depth_diff_max, depth_huber_delta=a.depth_diff_max / 4, intensity_huber_delta=0.1)
    crit = [T.OdometryConvergenceCriteria(20), T.OdometryConvergenceCriteria(10), T.OdometryConvergenceCriteria(5)]
    frames = []
    for (t, c), (_, d) in zip(rgb, depth):
        im = o3d.t.geometry.RGBDImage(o3d.t.io.read_image(os.path.join(a.seq, c)).to(o3c.float32), o3d.t.io.read_image(os.path.join(a.seq, d)))
        frames.append((float(t), im))
    pose, motion, lost = np.eye(4), np.eye(4), 0
    rows = []
    for i, (t, im) in enumerate(frames):
        if i > 0:
            try:
                res = T.rgbd_odometry_multi_scale(im, frames[i - 1][1], k, o3c.Tensor(motion), cam["depth_scale"], 1.0, crit, method, params)
                m = res.transformation.numpy()
                if np.all(np.isfinite(m)) and res.fitness > 0:
                    motion = m
                else:
                    lost += 1
            except RuntimeError:
                lost += 1
            pose = pose @ motion
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        rows.append(f"{t:.6f} {pose[0, 3]:.9f} {pose[1, 3]:.9f} {pose[2, 3]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    with open(a.out, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    print(f"{a.seq}: {len(frames)} frames, {lost} lost (odometry failed), written {a.out}")


if __name__ == "__main__":
    main()
