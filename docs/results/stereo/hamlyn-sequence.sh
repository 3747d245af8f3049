#!/usr/bin/env bash
# Builds a one-frame stereo sequence (TUM layout + rgb_right.txt + camera.toml's [right] table)
# from the Hamlyn silicone-heart pair in shared/data/hamlyn-heart-stereo/ (calibration as shipped:
# calib.l2r.4x4 is x_right = R x_left + t in millimetres, OpenCV's convention).
#   bash docs/results/stereo/hamlyn-sequence.sh ../shared/data/hamlyn-heart-stereo /tmp/hamlyn
set -euo pipefail
src=${1:?source folder}; out=${2:?output folder}
mkdir -p "$out/rgb" "$out/rgb_right"
cp "$src/f7_dynamic_deint_L_0100.png" "$out/rgb/0100.png"
cp "$src/f7_dynamic_deint_R_0100.png" "$out/rgb_right/0100.png"
echo "0.0 rgb/0100.png" > "$out/rgb.txt"
echo "0.0 rgb_right/0100.png" > "$out/rgb_right.txt"
read -r fxl _ cxl < <(sed -n 1p "$src/calib.left.intrinsic.txt"); read -r _ fyl cyl < <(sed -n 2p "$src/calib.left.intrinsic.txt")
read -r fxr _ cxr < <(sed -n 1p "$src/calib.right.intrinsic.txt"); read -r _ fyr cyr < <(sed -n 2p "$src/calib.right.intrinsic.txt")
mapfile -t m < "$src/calib.l2r.4x4"
read -r r00 r01 r02 t0 <<< "${m[0]}"; read -r r10 r11 r12 t1 <<< "${m[1]}"; read -r r20 r21 r22 t2 <<< "${m[2]}"
mm() { awk -v v="$1" 'BEGIN { printf "%.9f", v / 1000 }'; }
cat > "$out/camera.toml" <<TOML
width = 360
height = 288
fx = $fxl
fy = $fyl
cx = $cxl
cy = $cyl

[right]
fx = $fxr
fy = $fyr
cx = $cxr
cy = $cyr
rotation = [$r00, $r01, $r02, $r10, $r11, $r12, $r20, $r21, $r22]
translation_m = [$(mm "$t0"), $(mm "$t1"), $(mm "$t2")]
TOML
echo "written to $out"
