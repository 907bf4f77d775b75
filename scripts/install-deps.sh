#!/usr/bin/env bash
# Installs the Debian 12 packages pcl_animseg needs (skips apt when they are all present).
set -euo pipefail
PKGS=(build-essential cmake pkg-config libpcl-dev libopenmpi-dev libflann-dev libeigen3-dev
      libboost-program-options-dev libjemalloc-dev libgtest-dev libgmock-dev libbenchmark-dev ccache
      clang-14 libclang-rt-14-dev libomp-14-dev)
missing=()
for p in "${PKGS[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all packages present"
  exit 0
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
echo "install-deps: installing ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
