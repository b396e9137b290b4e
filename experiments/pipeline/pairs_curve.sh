#!/usr/bin/env bash
# Issue 68: how many generated pairs (and epochs) a segmenter needs. The first N pairs of a pipeline run's generated
# set (experiments/pipeline/pairs_subset.py: what generate n=N writes), a U-Net on each with the segment defaults, seeds
# 0-2, each scored on the set's annotated test ids by drgan.evaluate; the stage's wall time in each segment.log.
#
#   bash experiments/pipeline/pairs_curve.sh RUN ANNOTATED OUT "250 500" "0 1 2" [SEGMENT KEY=VALUE ...]
#   e.g. bash experiments/pipeline/pairs_curve.sh runs/pipeline/cej /work/data/emps/cej runs/pairs/cej "250 500" "0 1 2"
set -euo pipefail
run=$1; annotated=$2; out=$3; sizes=$4; seeds=$5; shift 5
mkdir -p "$out"
for n in $sizes; do
  python experiments/pipeline/pairs_subset.py "$run/generate" "$n" "$out/pairs_$n" >/dev/null
  for seed in $seeds; do
    tag=p${n}_s${seed}${*:+_$(echo "$*" | tr ' =/' '_-_')}
    [ -f "$out/$tag/metrics.json" ] || { start=$(date +%s)
      python -m drgan.segment data="$out/pairs_$n" out="$out/$tag" name=pairs seed="$seed" logger=none \
        trainer.enable_progress_bar=false "$@" >"$out/$tag.log" 2>&1
      echo "$tag segment_s $(( $(date +%s) - start ))" >>"$out/times.txt"; }
    [ -f "$out/ev_$tag/results.md" ] || python -m drgan.evaluate model="$out/$tag/checkpoints/last.ckpt" \
      data="$annotated" out="$out/ev_$tag" >"$out/ev_$tag.log" 2>&1
  done
done
