#!/usr/bin/env bash
# Sets everything up and runs the whole test suite (the README's test command; CI runs exactly this).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-deps.sh
bash scripts/build.sh
ctest --test-dir build -j"$(nproc)" --output-on-failure --timeout 900
# CI only (a few minutes on 2 cores): the io/common/evaluation/synth tests under ASan + UBSan,
# and every reader's fuzzer for 15 s (docs/reliability.md).
if [ -n "${CI:-}" ]; then
  bash scripts/asan.sh
  FUZZ_SECONDS=15 bash scripts/fuzz.sh
fi
