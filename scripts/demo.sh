#!/usr/bin/env bash
# Sets everything up and decomposes the shipped quadruped sequence into out/demo/ (the README demo).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh
rm -rf out/demo
./build/bin/animseg --input datasets/quadruped_points --output out/demo --png "$@"
echo "demo: labelled frames in out/demo (pcl_viewer out/demo/f000.pcd, key 5 or l for labels); picture: out/demo/contact_sheet.png"
if [ -x ./build/bin/animseg_eval ]; then
  ./build/bin/animseg_eval --pred out/demo --truth datasets/quadruped_points
fi
