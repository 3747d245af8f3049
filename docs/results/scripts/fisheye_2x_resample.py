#!/usr/bin/env python3
"""Resample a 640x640 equidistant render into the 320x320 pinhole camera by area sampling.

A one-off diagnostic of docs/results/camera-models.md ("The black border"): the
fisheye phantom rendered at twice the resolution (f = 320 px, centre 319.5) is brought into the
pinhole camera of the 320 phantom (f = 160 px, centre 159.5). Each target pixel is the mean of
4x4 bilinear taps spread over its area, each tap's ray sent through OpenCV's equidistant model
(theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)). Every target pixel is
then backed by at least 1.6 source pixels, the fisheye's rim included.

    python3 fisheye_2x_resample.py SRC_RGB_DIR DST_RGB_DIR [k1 k2 k3 k4]
"""
import os
import sys

import numpy as np
from PIL import Image

F_T, C_T = 160.0, 159.5
F_S, C_S = 320.0, 319.5
N_TAPS = 4


def taps(k):
    """Source positions (u, v) of the N_TAPS x N_TAPS sub-pixel rays of every target pixel."""
    ys, xs = np.mgrid[0:320, 0:320].astype(np.float64)
    offsets = (np.arange(N_TAPS) + 0.5) / N_TAPS - 0.5
    out = []
    for oy in offsets:
        for ox in offsets:
            x, y = (xs + ox - C_T) / F_T, (ys + oy - C_T) / F_T
            r = np.hypot(x, y)
            theta = np.arctan(r)
            t2 = theta * theta
            factor = 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
            s = np.where(r < 1e-12, 1.0, theta / np.maximum(r, 1e-12) * factor)
            out.append((F_S * x * s + C_S, F_S * y * s + C_S))
    return out


def bilinear(img, u, v):
    h, w = img.shape[:2]
    x0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    fx = np.clip(u - x0, 0, 1)[..., None]
    fy = np.clip(v - y0, 0, 1)[..., None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def main():
    src, dst = sys.argv[1], sys.argv[2]
    k = [float(v) for v in sys.argv[3:7]] or [0.05, -0.01, 0.002, -0.0005]
    positions = taps(k)
    for name in sorted(os.listdir(src)):
        img = np.asarray(Image.open(os.path.join(src, name)).convert("RGB")).astype(np.float64)
        mean = sum(bilinear(img, u, v) for u, v in positions) / len(positions)
        Image.fromarray(np.clip(np.rint(mean), 0, 255).astype(np.uint8)).save(os.path.join(dst, name))


if __name__ == "__main__":
    main()
