#!/usr/bin/env python3
"""OpenCV StereoSGBM as a peer of `stereo-sgm` (issue 19).

For a capsule-slam stereo sequence (TUM layout, rgb_right.txt, camera.toml with a [right] table),
writes a copy whose depth/ holds StereoSGBM's depth in the left camera's own image (16-bit PNG at
camera.toml's depth_scale), so that `capsule-slam run --set pipeline.depth=sensor` tracks and fuses
it, and prints its single-frame errors against the sequence's own depth/ (AbsRel, bad > 1 / 2 px,
coverage of the field of view) every `--every` frames.

  python3 -m venv /tmp/cvenv && /tmp/cvenv/bin/pip install opencv-python-headless numpy
  /tmp/cvenv/bin/python docs/results/stereo/opencv_sgbm.py SEQ OUT [--every 30]

SGBM settings: a Gaussian blur of both views (`--blur`, see below), then OpenCV's guidance (P1 = 8·3·b², P2 = 32·3·b², block 5, uniqueness 10, speckle
window 100 / range 2, disp12MaxDiff 1), the disparity range from 10–250 mm at the rig's f·b
(rounded up to a multiple of 16); rectification by cv2.stereoRectify (alpha 0, zero disparity).
"""
import argparse, math, os, shutil, sys, tomllib
import cv2
import numpy as np


def read_list(path):
    out = []
    for line in open(path):
        if line.startswith("#") or not line.strip():
            continue
        t, f = line.split()[:2]
        out.append((float(t), f))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("seq"); ap.add_argument("out"); ap.add_argument("--every", type=int, default=30)
    # Without a blur SGBM matches nothing on the phantom's noisy pairs (coverage 0.1 %); of
    # σ = 1, 2, 3 px, 2 gave the fewest bad pixels (preset 1 frame 5: coverage 40 %, bad > 1 px 54 %).
    ap.add_argument("--blur", type=float, default=2.0, help="Gaussian σ (px) applied to both rectified views first; 0: none")
    a = ap.parse_args()
    cam = tomllib.load(open(os.path.join(a.seq, "camera.toml"), "rb"))
    r = cam["right"]
    w, h = cam["width"], cam["height"]
    K1 = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], float)
    K2 = np.array([[r["fx"], 0, r["cx"]], [0, r["fy"], r["cy"]], [0, 0, 1]], float)
    D1 = np.zeros(5); D2 = np.zeros(5)  # the phantom and Hamlyn pairs have no distortion
    R = np.array(r["rotation"], float).reshape(3, 3); T = np.array(r["translation_m"], float).reshape(3, 1)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K1, D1, K2, D2, (w, h), R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    m1 = cv2.initUndistortRectifyMap(K1, D1, R1, P1, (w, h), cv2.CV_32FC1)
    m2 = cv2.initUndistortRectifyMap(K2, D2, R2, P2, (w, h), cv2.CV_32FC1)
    f, b = P1[0, 0], abs(P2[0, 3] / P2[0, 0])
    fb = f * b
    n_disp = int(math.ceil(fb / 0.01 / 16.0)) * 16
    bs = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=n_disp, blockSize=bs, P1=8 * 3 * bs * bs, P2=32 * 3 * bs * bs,
                                 disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM)
    # Where each left pixel lands in the rectified left image, and its ray there.
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], 1)[:, None, :], K1, D1, R=R1, P=P1).reshape(h, w, 2)
    scale = cam.get("depth_scale", 5000.0)
    fov_r = cam.get("fov_radius_px")
    fov = np.ones((h, w), bool) if fov_r is None else (u - cam["cx"]) ** 2 + (v - cam["cy"]) ** 2 <= fov_r ** 2
    os.makedirs(a.out, exist_ok=True)
    for name in os.listdir(a.seq):
        if name in ("depth", "depth.txt", "camera.toml"):
            continue
        dst = os.path.join(a.out, name)
        if not os.path.lexists(dst):
            os.symlink(os.path.abspath(os.path.join(a.seq, name)), dst)
    # The same noise model as stereo-sgm's (σ_d 0.3 px, correlation 8 px), for the trackers.
    text = open(os.path.join(a.seq, "camera.toml")).read()
    head, _, rest = text.partition("[right]")
    head += f"depth_noise = {{ quadratic_per_m = {0.3 / fb:.6f}, correlation_px = 8.0 }}\n\n"
    open(os.path.join(a.out, "camera.toml"), "w").write(head + "[right]" + rest)
    os.makedirs(os.path.join(a.out, "depth"), exist_ok=True)
    left, right = read_list(os.path.join(a.seq, "rgb.txt")), read_list(os.path.join(a.seq, "rgb_right.txt"))
    depth_list = read_list(os.path.join(a.seq, "depth.txt")) if os.path.exists(os.path.join(a.seq, "depth.txt")) else []
    lines, stats = [], []
    for i, ((t, lf), (_, rf)) in enumerate(zip(left, right)):
        L = cv2.imread(os.path.join(a.seq, lf)); Rr = cv2.imread(os.path.join(a.seq, rf))
        Lr = cv2.remap(L, m1[0], m1[1], cv2.INTER_LINEAR); Rrr = cv2.remap(Rr, m2[0], m2[1], cv2.INTER_LINEAR)
        if a.blur > 0:
            Lr, Rrr = cv2.GaussianBlur(Lr, (0, 0), a.blur), cv2.GaussianBlur(Rrr, (0, 0), a.blur)
        d = sgbm.compute(Lr, Rrr).astype(np.float32) / 16.0
        xi = np.clip(np.round(pts[..., 0]).astype(int), 0, w - 1); yi = np.clip(np.round(pts[..., 1]).astype(int), 0, h - 1)
        dl = d[yi, xi]
        ok = (dl > 0.5) & fov & (pts[..., 0] >= 0) & (pts[..., 0] < w) & (pts[..., 1] >= 0) & (pts[..., 1] < h)
        zr = np.where(ok, fb / np.maximum(dl, 1e-6), 0.0)
        # The rectified point back in the left camera: z of R1ᵀ · (x zr, y zr, zr).
        xr = (pts[..., 0] - P1[0, 2]) / f; yr = (pts[..., 1] - P1[1, 2]) / P1[1, 1]
        z = np.where(ok, (R1[0, 2] * xr + R1[1, 2] * yr + R1[2, 2]) * zr, 0.0)
        z[(z < 0.01) | (z > 0.25)] = 0.0
        name = f"depth/{os.path.basename(lf)}"
        cv2.imwrite(os.path.join(a.out, name), np.round(z * scale).astype(np.uint16))
        lines.append(f"{t:.6f} {name}")
        if depth_list and i % a.every == 0:
            gt = cv2.imread(os.path.join(a.seq, depth_list[i][1]), cv2.IMREAD_UNCHANGED).astype(np.float64) / scale
            both = (z > 0) & (gt > 0)
            rel = np.abs(z[both] - gt[both]) / gt[both]
            dd = np.abs(fb / z[both] - fb / gt[both])
            stats.append((rel.mean(), (dd > 1).mean(), (dd > 2).mean(), both.sum() / ((gt > 0) & fov).sum()))
    open(os.path.join(a.out, "depth.txt"), "w").write("# StereoSGBM depth (opencv_sgbm.py)\n" + "\n".join(lines) + "\n")
    if stats:
        s = np.array(stats).mean(0)
        print(f"StereoSGBM ({cv2.__version__}, {n_disp} disparities, block {bs}, blur {a.blur} px) on {len(stats)} frames of {a.seq}: "
              f"AbsRel {s[0]:.4f}, bad > 1 px {100 * s[1]:.2f} %, > 2 px {100 * s[2]:.2f} %, coverage {100 * s[3]:.1f} % of the field of view")
    print(f"written to {a.out}")


if __name__ == "__main__":
    sys.exit(main())
