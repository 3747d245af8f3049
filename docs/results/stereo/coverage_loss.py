"""Where a stereo depth estimate leaves holes, of the pixels both cameras see.

Usage: python coverage_loss.py SEQ DEPTH_OUT [FRAME ...]
  SEQ        a stereo phantom (`capsule-slam synth --stereo`): depth/, specular/, camera.toml
  DEPTH_OUT  `capsule-slam depth --config apps/configs/stereo-capsule.toml --input SEQ --out DEPTH_OUT`
  FRAME      frame indices (default: every 6th of 60); the first one is drawn to DEPTH_OUT/holes.png
             (red: elsewhere, blue: within 10 px of either view's rim, yellow: a highlight)

Needs numpy and opencv-python-headless. Assumes a rectified rig of two identical cameras
(what `synth --stereo` writes): the right pixel of a left pixel is x - f b / z on the same row.
"""
import sys
import tomllib

import cv2
import numpy as np

seq, out = sys.argv[1], sys.argv[2]
cam = tomllib.load(open(f"{seq}/camera.toml", "rb"))
f, cx, cy, rim = cam["fx"], cam["cx"], cam["cy"], cam["fov_radius_px"]
b = -cam["right"]["translation_m"][0]
scale = cam.get("depth_scale", 5000.0)
frames = [int(a) for a in sys.argv[3:]] or list(range(0, 60, 6))
total = {}
for n, i in enumerate(frames):
    gt = cv2.imread(f"{seq}/depth/{i:06d}.png", -1).astype(float) / scale
    est = cv2.imread(f"{out}/{i:04d}_depth.png", -1).astype(float) / scale
    spec = cv2.imread(f"{seq}/specular/{i:06d}.png", -1)
    spec = spec.max(axis=2) if spec.ndim == 3 else spec
    h, w = gt.shape
    ys, xs = np.mgrid[0:h, 0:w]
    xr = xs - f * b / np.where(gt > 0, gt, 1.0)
    radius_l = np.hypot(xs - cx, ys - cy)
    radius_r = np.hypot(xr - cx, ys - cy)
    both = (radius_l <= rim) & (gt > 0) & (radius_r <= rim)
    hole = both & (est <= 0)
    glint = cv2.dilate((spec > 20).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    at_rim = (radius_l > rim - 10) | (radius_r > rim - 10)
    row = {
        "both see": both.sum(),
        "holes": hole.sum(),
        "on a highlight": (hole & glint).sum(),
        "within 10 px of a rim": (hole & ~glint & at_rim).sum(),
        "elsewhere": (hole & ~glint & ~at_rim).sum(),
    }
    for k, v in row.items():
        total[k] = total.get(k, 0) + v
    print(i, {k: f"{100 * v / row['both see']:.1f} %" for k, v in row.items() if k != "both see"})
    if n == 0:
        img = cv2.imread(f"{seq}/rgb/{i:06d}.png")
        vis = (img * 0.5).astype(np.uint8)
        vis[hole & ~glint & ~at_rim] = (0, 0, 255)
        vis[hole & ~glint & at_rim] = (255, 0, 0)
        vis[hole & glint] = (0, 255, 255)
        cv2.imwrite(f"{out}/holes.png", np.hstack([img, vis]))
print("all", {k: f"{100 * v / total['both see']:.1f} %" for k, v in total.items() if k != "both see"})
