#!/usr/bin/env python3
"""Copy a sequence folder with its colour images perturbed by a tiny dither.

Each colour value gets uniform noise in [-A, A] gray levels (default A = 1) and is rounded back to
8 bits; with A = 1 about a third of the values move by one level. Everything else (depth, ground
truth, camera.toml, light.toml) is copied unchanged. Used to measure how much a run's ATE moves
under a perturbation far below the phantom's own sensor noise (about 2.6 gray levels), and so
found the black border's bug (docs/results/camera-models.md, "The black border").

    python3 dither.py SRC DST --seed S [--amplitude A]
"""
import argparse
import os
import shutil

import numpy as np
from PIL import Image


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--amplitude", type=float, default=1.0, help="gray levels")
    a = ap.parse_args()
    if os.path.exists(a.dst):
        raise SystemExit(f"{a.dst} exists: give a new folder")
    shutil.copytree(a.src, a.dst)
    rng = np.random.default_rng(a.seed)
    rgb = os.path.join(a.dst, "rgb")
    for name in sorted(os.listdir(rgb)):
        path = os.path.join(rgb, name)
        img = np.asarray(Image.open(path).convert("RGB")).astype(np.float64)
        img += rng.uniform(-a.amplitude, a.amplitude, img.shape)
        Image.fromarray(np.clip(np.rint(img), 0, 255).astype(np.uint8)).save(path)


if __name__ == "__main__":
    main()
