#!/usr/bin/env bash
# `make demo`: the main job end to end on the embedded default (the synthetic
# fixture): every paper table at smoke scale with figures; prints where everything went.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-/usr/bin/python3}
BUILD=${BUILD:-build}
PROFILE=${PROFILE:-smoke}
MC="$BUILD/motionctl"
OUT="runs/demo"
mkdir -p "$OUT"

echo "== BLAS check"
"$MC" bench blas

echo "== fixture ($PROFILE)"
"$MC" fixture "configs/data/$PROFILE.yaml"
DATA="data/fixture_$PROFILE.h5"

echo "== figures of the dataset"
"$PYTHON" tools/render_motion.py "$DATA" --out "$OUT/clips" --count 4 --frames 8 --gif
"$PYTHON" tools/dataset_stats.py "$DATA" --out "$OUT/stats"

echo "== every table of both papers ($PROFILE profile): train what is missing, run, evaluate, render"
status=0
PYTHON="$PYTHON" "$MC" reproduce --profile "$PROFILE" || status=$?

echo
echo "demo outputs:"
echo "  dataset:          $DATA"
echo "  clip renders:     $OUT/clips/"
echo "  dataset stats:    $OUT/stats/"
echo "  tables:           results/$PROFILE/<paper>/tableN.{md,csv,tex}"
echo "  claims summary:   results/$PROFILE/summary.md"
echo "  figures:          results/$PROFILE/figures/"
echo "  raw metrics:      results/$PROFILE/results.h5"
if [ -f "results/$PROFILE/summary.md" ]; then
  echo
  sed -n '1,40p' "results/$PROFILE/summary.md"
fi
exit $status
