#!/usr/bin/env bash
# Transmission labels, first hit against the farthest outline: one GAN's pairs labelled both ways, U-Nets on each (3 seeds),
# each scored on its own held-out pairs (closed loop) and on the annotated test ids. Resumable.
#
#   bash experiments/statistics/transmission_labels.sh PIPELINE_RUN BEFORE_SRC DATASET OUT
#
# PIPELINE_RUN: a finished drgan.pipeline run on transmission images (its train/ GAN and the generate command it ran);
# BEFORE_SRC: the src/ folder of a checkout with the first-hit labelling (a `git worktree` of 86ca140). The same
# pairs are rendered from the same GAN by both checkouts (this one: OUT/gen_after).
set -euo pipefail
RUN=${1:?usage: transmission_labels.sh PIPELINE_RUN BEFORE_SRC DATASET OUT}
BEFORE_SRC=${2:?}
DATASET=${3:?}
OUT=${4:?}
mkdir -p "$OUT"
args=$(python -c "import json,sys; a=json.load(open(sys.argv[1]))['stages']['generate']['args']; \
print(' '.join(x for x in a if not x.startswith('out=')))" "$RUN/pipeline.json")
if [ ! -f "$OUT/gen_before/manifest.json" ]; then
  # shellcheck disable=SC2086
  PYTHONPATH=$BEFORE_SRC python -m drgan.generate $args out="$OUT/gen_before" > "$OUT/gen_before.log" 2>&1
fi
if [ ! -f "$OUT/gen_after/manifest.json" ]; then
  # shellcheck disable=SC2086
  python -m drgan.generate $args out="$OUT/gen_after" > "$OUT/gen_after.log" 2>&1
fi
for labels in before after; do
  gen=$OUT/gen_$labels
  SEEDS=${SEEDS:-0 1 2} bash experiments/statistics/closed_loop.sh "$gen" "$OUT/$labels" \
    check_fraction=0.05 > /dev/null
  for run in "$OUT/$labels"/default_*; do
    [ -d "$run" ] || continue
    ev=$OUT/ev_${labels}_s${run##*_}  # test ids (evaluate's default subset), read by pairs_table.py
    [ -f "$ev/results.csv" ] || python -m drgan.evaluate model="$run/checkpoints/last.ckpt" data="$DATASET" \
      out="$ev" > "$ev.log" 2>&1
  done
done
python experiments/statistics/closed_loop_table.py "$OUT"/*/default_*/metrics.json
python experiments/pipeline/pairs_table.py "$OUT"
