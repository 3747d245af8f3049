"""The ex-vivo acceptance's score, rehearsed on a still stereo phantom (issue 19).

Usage: python ct_score.py SEQ MAP_PLY

"CT points": the true surface the left camera sees at frame 0 (its exact depth, `depth/000000.png`,
back-projected through the lens of `camera.toml`), in the still camera's frame. Each is scored by
its distance to the nearest surfel of the map (`map.ply`, written in the first camera's frame),
with no alignment. Prints the median, the RMSE and the shares within 1 and 2 mm, over all CT
points and over those inside a pinhole image of the file's intrinsics and size (what the
undistortion keeps with `input.undistorted_view = "source"`). Needs numpy, scipy, opencv-python-headless.
"""
import sys
import tomllib

import cv2
import numpy as np
from scipy.spatial import cKDTree


def read_ply_xyz(path):
    with open(path, "rb") as f:
        head = b""
        while not head.endswith(b"end_header\n"):
            line = f.readline()
            if not line:
                sys.exit(f"{path}: no end_header")
            head += line
        lines = head.decode().splitlines()
        if "format binary_little_endian 1.0" not in lines:
            sys.exit(f"{path}: expected a binary little-endian PLY")
        n = int([l for l in lines if l.startswith("element vertex")][0].split()[2])
        types = {"float": "f4", "uchar": "u1", "uint": "u4", "int": "i4", "double": "f8"}
        dt = np.dtype([(p.split()[2], "<" + types[p.split()[1]]) for p in lines if p.startswith("property")])
        m = np.frombuffer(f.read(n * dt.itemsize), dtype=dt, count=n)
    return np.column_stack([m["x"], m["y"], m["z"]]).astype(np.float64)


def main():
    seq, ply = sys.argv[1], sys.argv[2]
    cam = tomllib.load(open(f"{seq}/camera.toml", "rb"))
    k = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    dist = np.array(cam.get("distortion", {}).get("coefficients", []), float)
    depth = cv2.imread(f"{seq}/depth/000000.png", cv2.IMREAD_UNCHANGED).astype(np.float64) / cam["depth_scale"]
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    px = np.stack([u, v], 1).astype(np.float64)
    if dist.size:
        xy = cv2.undistortPoints(px.reshape(-1, 1, 2), k, dist).reshape(-1, 2)
    else:
        xy = (px - k[:2, 2]) / [k[0, 0], k[1, 1]]
    ct = np.column_stack([xy * z[:, None], z])
    surfels = read_ply_xyz(ply)
    if len(surfels) == 0:
        print(f"{seq}: {len(ct)} CT points, the map is empty")
        return
    d_mm = cKDTree(surfels).query(ct)[0] * 1e3
    pin = xy * [k[0, 0], k[1, 1]] + k[:2, 2]
    inside = (pin[:, 0] >= 0) & (pin[:, 0] <= cam["width"] - 1) & (pin[:, 1] >= 0) & (pin[:, 1] <= cam["height"] - 1)

    def line(d):
        return f"median {np.median(d):.3f} mm, RMSE {np.sqrt(np.mean(d ** 2)):.3f} mm, within 1 mm {100 * np.mean(d < 1):.1f} %, within 2 mm {100 * np.mean(d < 2):.1f} %"

    print(f"{seq}: {len(ct)} CT points, {len(surfels)} surfels: {line(d_mm)}")
    print(f"  inside the file's pinhole image ({100 * inside.mean():.1f} % of the CT points): {line(d_mm[inside])}")


if __name__ == "__main__":
    main()
