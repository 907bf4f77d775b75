#!/usr/bin/env bash
# Builds the libFuzzer targets (Clang, ASan + UBSan; build directory build-fuzz or $FUZZ_BUILD_DIR)
# and runs each for FUZZ_SECONDS (default 20) seconds. Fails on any finding: a crash, a sanitizer
# report, an exception other than pcl_animseg::Error, a timeout or running out of memory.
#
# Seeds: fuzz/corpus/<target>/ (small, committed). The corpus grown by the runs is kept in
# $FUZZ_CORPUS_DIR/<target>/ (default build-fuzz/corpus) and reused by the next run. A crashing
# input is saved as $FUZZ_CORPUS_DIR/../artifacts/<target>-crash-*; reproduce with
# `build-fuzz/fuzz/fuzz_<target> FILE`, then add it to test/io/test_regressions.cpp.
#   FUZZ_SECONDS=60 bash scripts/fuzz.sh            all targets
#   bash scripts/fuzz.sh ply pcd                    some targets
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD=${FUZZ_BUILD_DIR:-build-fuzz}
SECONDS_EACH=${FUZZ_SECONDS:-20}
CORPUS=${FUZZ_CORPUS_DIR:-$BUILD/corpus}
ARTIFACTS=$CORPUS/../artifacts
JOBS=${JOBS:-2}
CLANG=${CLANG:-$(command -v clang++ || command -v clang++-14 || true)}
if [ -z "$CLANG" ]; then
  echo "fuzz: clang++ not found (scripts/install-deps.sh installs clang-14)" >&2
  exit 1
fi
CLANG_C=${CLANG/clang++/clang}
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  for f in fuzz/fuzz_*.cpp; do t=$(basename "$f" .cpp); targets+=("${t#fuzz_}"); done
fi
CC="$CLANG_C" CXX="$CLANG" cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DPCL_ANIMSEG_BUILD_FUZZERS=ON -DPCL_ANIMSEG_WITH_CUDA=OFF -DPCL_ANIMSEG_BUILD_TESTS=OFF \
  -DPCL_ANIMSEG_BUILD_BENCHMARKS=OFF >/dev/null
cmake --build "$BUILD" -j"$JOBS" --target "${targets[@]/#/fuzz_}"
mkdir -p "$ARTIFACTS"
export OMP_NUM_THREADS=1
# Leaks are not checked: PCL, FLANN and the OpenMP runtime keep process-lifetime allocations.
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=0}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-halt_on_error=1:print_stacktrace=1}
failed=()
for t in "${targets[@]}"; do
  mkdir -p "$CORPUS/$t"
  echo "fuzz: $t for ${SECONDS_EACH}s"
  log="$BUILD/fuzz_$t.log"
  # New inputs go into the first corpus directory (the kept one); the seeds are only read.
  if "$BUILD/fuzz/fuzz_$t" -max_total_time="$SECONDS_EACH" -timeout=10 -rss_limit_mb=2048 \
      -max_len=8192 -print_final_stats=1 -artifact_prefix="$ARTIFACTS/$t-" \
      "$CORPUS/$t" "fuzz/corpus/$t" >"$log" 2>&1; then
    grep -E "^stat::number_of_executed_units|^stat::new_units_added" "$log" | tr '\n' ' '
    echo
  else
    failed+=("$t")
    tail -n 60 "$log" >&2
  fi
done
if [ ${#failed[@]} -ne 0 ]; then
  echo "fuzz: FINDINGS in ${failed[*]} (inputs in $ARTIFACTS)" >&2
  exit 1
fi
echo "fuzz: ${#targets[@]} targets, ${SECONDS_EACH}s each, no finding"
