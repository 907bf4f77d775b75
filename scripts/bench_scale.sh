#!/usr/bin/env bash
# Scale benchmark (not a CI test): generates a FRAMES x POINTS sequence with animseg_synth (default
# 50 x 100000 = 5 M points) and runs animseg on it under /usr/bin/time -v; prints wall time and peak
# RSS (goal: <= 4 GB for 5 M points). Uses the tools of $BUILD (default build).
#   FRAMES=50 POINTS=100000 TIMEOUT=3600 bash scripts/bench_scale.sh [extra animseg options]
# The 800k-point pipeline benchmark (stage shares) is FRAMES=48 POINTS=16667.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD=${BUILD:-build}
FRAMES=${FRAMES:-50}
POINTS=${POINTS:-100000}
TIMEOUT=${TIMEOUT:-3600}
WORK=${WORK:-$(mktemp -d "${TMPDIR:-/tmp}/animseg_scale_XXXXXX")}
PLAN=${PLAN:-humanoid}
for t in animseg animseg_synth; do
  [ -x "$BUILD/bin/$t" ] || { echo "bench_scale: $BUILD/bin/$t not built" >&2; exit 1; }
done
echo "bench_scale: $FRAMES frames x $POINTS points ($PLAN) in $WORK"
if [ ! -f "$WORK/in/synth.json" ]; then
  /usr/bin/time -f "synth: %e s, peak RSS %M KB" "$BUILD/bin/animseg_synth" --quiet --plan "$PLAN" \
    --frames "$FRAMES" --points "$POINTS" --seed 1 --output "$WORK/in"
fi
du -sh "$WORK/in"
rc=0
/usr/bin/time -v timeout "$TIMEOUT" "$BUILD/bin/animseg" --input "$WORK/in" --output "$WORK/out" \
  "$@" 2>"$WORK/animseg.err" || rc=$?
grep -vE "^\s" "$WORK/animseg.err" | tail -n 30 || true
grep -E "Elapsed \(wall|Maximum resident|User time|System time|Exit status" "$WORK/animseg.err" || true
# Stage timings (refine + hierarchy against the total: issue goal <= 20% at 800k points).
[ -f "$WORK/out/summary.json" ] && grep -o '"timings_s": {[^}]*}' "$WORK/out/summary.json" || true
rss_kb=$(awk -F: '/Maximum resident/ {gsub(/ /, "", $2); print $2}' "$WORK/animseg.err")
[ -n "$rss_kb" ] && echo "bench_scale: peak RSS $((rss_kb / 1024)) MB (goal <= 4096 MB), exit $rc"
[ "$rc" -eq 124 ] && echo "bench_scale: animseg stopped by the ${TIMEOUT}s timeout"
exit "$rc"
