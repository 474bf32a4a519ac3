#!/usr/bin/env bash
# `make demo`: the main job end to end on the embedded default (the synthetic
# fixture) at smoke scale, then figures; prints where everything went.
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

echo "== training loop on a real model (motion autoencoder)"
"$MC" train configs/train/autoencoder_smoke.yaml

echo
echo "demo outputs:"
echo "  dataset:          $DATA"
echo "  clip renders:     $OUT/clips/"
echo "  dataset stats:    $OUT/stats/"
echo "  autoencoder run:  runs/autoencoder/ (config.yaml, metrics.csv, checkpoints/, summary.csv)"
