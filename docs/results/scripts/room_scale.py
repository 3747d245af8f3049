#!/usr/bin/env python3
"""A phantom sequence scaled to room size, with Kinect-like depth: a stand-in for the real
room-scale RGB-D frames that issue 17's acceptance runs (`apps/configs/indoor-rgbd.toml`) and
that cannot be downloaded on this machine.

Every depth and every ground-truth translation is multiplied by K (40 turns the phantom's
20–90 mm into 0.8–3.6 m), the images are kept, `camera.toml` loses the phantom's round field of
view and its `depth_noise` (a TUM-style camera file declares none). With `--kinect` the depth
gets a Kinect v1's error: the axial σ of Nguyen, Izadi and Lovell (3DIMPVT 2012),
σ(z) = 1.2 mm + 1.9 mm·m⁻²·(z − 0.4 m)², drawn per pixel, then the disparity of a 580 px ×
75 mm rig rounded to 1/8 px (steps of z²/(8·f·b): 9 mm at 2 m). The clean scaled depth is the
ground truth. The surface scan is not written (its metric is turned off with a warning).

    python3 room_scale.py SRC DST [--scale 40] [--kinect] [--seed 7]

Needs numpy and Pillow.
"""
import argparse
import os
import shutil

import numpy as np
from PIL import Image


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--scale", type=float, default=40.0)
    ap.add_argument("--kinect", action="store_true")
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args()
    shutil.rmtree(a.dst, ignore_errors=True)
    os.makedirs(os.path.join(a.dst, "depth"))
    shutil.copytree(os.path.join(a.src, "rgb"), os.path.join(a.dst, "rgb"))
    for f in ["rgb.txt", "depth.txt"]:
        shutil.copy(os.path.join(a.src, f), os.path.join(a.dst, f))
    with open(os.path.join(a.src, "camera.toml")) as f:
        cam = f.read().split("[depth_noise]")[0]
    cam = "".join(line + "\n" for line in cam.splitlines() if not line.startswith("fov_radius_px"))
    scale_png = None
    for line in cam.splitlines():
        if line.startswith("depth_scale"):
            scale_png = float(line.split("=")[1])
    with open(os.path.join(a.dst, "camera.toml"), "w") as f:
        f.write(cam)
    with open(os.path.join(a.src, "groundtruth.txt")) as src, open(os.path.join(a.dst, "groundtruth.txt"), "w") as dst:
        for line in src:
            if line.startswith("#") or not line.strip():
                dst.write(line)
                continue
            v = line.split()
            v[1:4] = ["%.9f" % (float(x) * a.scale) for x in v[1:4]]
            dst.write(" ".join(v) + "\n")
    rng = np.random.default_rng(a.seed)
    fb_px_m = 580.0 * 0.075
    for name in sorted(os.listdir(os.path.join(a.src, "depth"))):
        d = np.asarray(Image.open(os.path.join(a.src, "depth", name))).astype(np.float64) / scale_png * a.scale
        valid = d > 0
        if a.kinect:
            d = d + (0.0012 + 0.0019 * (d - 0.4) ** 2) * rng.standard_normal(d.shape)
            disparity = np.round(fb_px_m / np.maximum(d, 1e-3) * 8.0) / 8.0
            d = fb_px_m / np.maximum(disparity, 1e-6)
            d[~valid] = 0.0
        out = np.clip(np.round(d * scale_png), 0, 65535).astype(np.uint16)
        Image.fromarray(out).save(os.path.join(a.dst, "depth", name))
    print(f"{a.dst}: {a.src} scaled {a.scale}×{', Kinect v1 depth error' if a.kinect else ''}")


if __name__ == "__main__":
    main()
