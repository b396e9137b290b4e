#!/usr/bin/env bash
# Issue 66: the correction loop measured. A pipeline run's segmenter fine-tuned on N annotated train images taken as a
# user's corrections (make_fixes.py; each seed corrects other images), against a real-only U-Net trained on the same N
# images (segment real= with their split) and the pipeline's own synthetic-only one (RUN: a pipeline run or a segment
# run folder); all scored on the test ids.
#
#   bash experiments/finetune/loop.sh RUN DATASET OUT "1 2 4" "0 1 2" [FINETUNE KEY=VALUE ...]
#   KINDS="ft real reallong" (default "ft real"); reallong: the real-only U-Net with CROPS (400) crops per epoch over
#   its N images: 12 epochs of 600 steps, the fine-tuning's on tio2_tsem's pairs (the default real= gives 6 N steps)
#   python experiments/pipeline/pairs_table.py OUT          # the table (ev_base: the pipeline's segmenter)
set -euo pipefail
run=$1; dataset=$2; out=$3; sizes=$4; seeds=$5; shift 5
mkdir -p "$out"
quiet="logger=none trainer.enable_progress_bar=false"
base="$run/checkpoints/last.ckpt"; [ -d "$run/segment" ] && base="$run/segment/checkpoints/last.ckpt"  # RUN: a
# pipeline run or a segment run folder
[ -f "$out/ev_base/results.md" ] || python -m drgan.evaluate model="$base" \
  data="$dataset" out="$out/ev_base" >"$out/ev_base.log" 2>&1
for seed in $seeds; do
  for n in $sizes; do
    fixes="$out/fixes_n${n}_s${seed}"
    [ -f "$fixes/split.json" ] || python experiments/finetune/make_fixes.py "$dataset" "$n" "$seed" "$fixes" \
      >"$fixes.ids"
    for kind in ${KINDS:-ft real}; do
      tag=${kind}_n${n}_s${seed}
      if [ ! -f "$out/$tag/metrics.json" ]; then
        start=$(date +%s)
        if [ "$kind" = ft ]; then
          python -m drgan.segment finetune="$run" corrected="$fixes" correction.images="$dataset/images" \
            out="$out/$tag" name=finetune seed="$seed" $quiet "$@" >"$out/$tag.log" 2>&1
        elif [ "$kind" = real ]; then
          python -m drgan.segment real="$dataset" split="$fixes/split.json" out="$out/$tag" name=real \
            seed="$seed" $quiet >"$out/$tag.log" 2>&1
        else  # reallong: the real-only U-Net given the fine-tuning's steps (CROPS crops per epoch over the N images)
          python -m drgan.segment real="$dataset" split="$fixes/split.json" out="$out/$tag" name=real \
            seed="$seed" loader.samples_per_pair=$(( (${CROPS:-400} + n / 2) / n )) $quiet >"$out/$tag.log" 2>&1
        fi
        echo "$tag segment_s $(( $(date +%s) - start ))" >>"$out/times.txt"
      fi
      [ -f "$out/ev_$tag/results.md" ] || python -m drgan.evaluate model="$out/$tag/checkpoints/last.ckpt" \
        data="$dataset" out="$out/ev_$tag" >"$out/ev_$tag.log" 2>&1
    done
  done
done
