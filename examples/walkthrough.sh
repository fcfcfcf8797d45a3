#!/usr/bin/env bash
# Five-minute walkthrough on simulated images: calibrate from two plate images, then turn a
# seabed image into a range map and compare it with the simulator's ground truth.
# Usage: bash examples/walkthrough.sh [WORK_FOLDER]   (default: a new temporary folder)
set -euo pipefail
# The checkout's .venv (where deploy/install.sh installs uwcam), else uwcam and python3 on PATH.
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [ -x "$repo/.venv/bin/uwcam" ]; then
  uwcam() { "$repo/.venv/bin/uwcam" "$@"; }
  python=$repo/.venv/bin/python
elif command -v uwcam > /dev/null; then
  python=python3  # with numpy, as uwcam's own
else
  echo "uwcam is not installed: run 'bash deploy/install.sh' in $repo first" >&2
  exit 1
fi
work=${1:-$(mktemp -d -t uwcam-walkthrough.XXXX)}
mkdir -p "$work" && cd "$work"
echo "working in $work"

# A lamp 0.3 m to the camera's right, in the water of the method's textbook study:
# attenuation 0.46/0.11/0.06 1/m (R/G/B), forward scatter B = 0.010, light backscatter.
water=(--water ideal --forward-blur 0.010 --scatter-attenuation 0.44,0.09,0.04 --backscatter 0.0002 --lamp-offset 0.3,0,0)

echo "1. image the grey calibration plate at 1 m and 2 m"
uwcam simulate --scene plate --range 1 --peak 45000 --seed 1 -o plate_1m.tif "${water[@]}" | tee sim.txt
uwcam simulate --scene plate --range 2 --peak 45000 --seed 2 -o plate_2m.tif "${water[@]}" > /dev/null
intrinsics=$(sed -n 's/^intrinsics //p' sim.txt)
dark=$(sed -n 's/^dark level \([0-9.]*\) DN.*/\1/p' sim.txt)

echo "2. calibrate"
uwcam calibrate plate_1m.tif plate_2m.tif --distance 1 --distance 2 --rig grey-plate \
      --intrinsics "$intrinsics" --dark-level "$dark,$dark,$dark" --lamp-offset 0.3,0,0 -o profile.yaml

echo "3. a brick half-buried in a grey seabed, 2.5 m below the camera, and a frame of open water"
echo "   (turn the camera to empty water, same exposure and lamp) for the backscatter pattern"
uwcam simulate --scene brick --range 2.5 --material grey --seed 3 -o brick.png --truth truth.npy "${water[@]}" | tee scene.txt > /dev/null
exposure=$(sed -n 's/.*exposure //p' scene.txt)
uwcam simulate --scene open-water --range 2.5 --seed 4 --exposure "$exposure" -o open_water.png "${water[@]}" > /dev/null

echo "4. range it, first as is, then with backscatter compensated"
uwcam range profile.yaml brick.png -o range_raw.npy --smooth mean
uwcam range profile.yaml brick.png -o range.npy --variance variance.npy --reasons reasons.npy --smooth mean \
      --compensate-backscatter --open-water open_water.png

"$python" - <<'PY'
import numpy as np
t = np.load("truth.npy")
for name in ("range_raw.npy", "range.npy"):
    r = np.load(name)
    e = r - t
    print(f"5. {name}: rms error {np.sqrt(np.nanmean(e**2)) * 100:.1f} cm, bias {np.nanmean(e) * 100:+.1f} cm, "
          f"{np.isfinite(r).mean():.0%} of pixels valid; brick top at {np.nanmedian(r[232:248, 312:328]):.2f} m (truth 2.40 m)")
v = np.load("variance.npy")
print(f"   predicted σ (compensated) {np.sqrt(np.nanmean(v)) * 100:.1f} cm; reasons per pixel in reasons.npy")
PY
