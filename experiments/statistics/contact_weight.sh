#!/usr/bin/env bash
# Issue 27: U-Nets trained with the contact-weighted cross-entropy (model.contact_weight, drgan.segmenters.module),
# against merged touching particles; every run resumable (rerun the same command to continue).
#
#   bash experiments/statistics/contact_weight.sh tio2_sem|tio2_tsem [OUT] [KINDS]
#
# OUT (default runs/statistics/SET) must hold the generated pairs of run.sh's generate step (OUT/synthetic).
# KINDS: "synthetic real" (default) or one of them. Env: SEEDS ("0 1 2"), EPOCHS (12), WEIGHT (10: Ronneberger's w0),
# REACH (3 px). U-Nets go to OUT/seg_<kind>_cw<WEIGHT>_<seed>, evaluations on the test ids to OUT/eval_<kind>_cw<WEIGHT>.
set -euo pipefail
SET=${1:?usage: contact_weight.sh tio2_sem|tio2_tsem [OUT] [KINDS]}
OUT=${2:-runs/statistics/$SET}
KINDS=${3:-synthetic real}
DATA=${DRGAN_DATA:-../shared/datasets}/$SET
SEEDS=${SEEDS:-0 1 2}
EPOCHS=${EPOCHS:-12}
WEIGHT=${WEIGHT:-10}
REACH=${REACH:-3}
for kind in $KINDS; do
  for seed in $SEEDS; do
    run=$OUT/seg_${kind}_cw${WEIGHT}_$seed
    [ -f "$run/metrics.json" ] && continue
    resume=(); [ -f "$run/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
    if [ "$kind" = synthetic ]; then src=(data="$OUT/synthetic"); else src=(real="$DATA" contour_px=1); fi
    python -m drgan.segment "${src[@]}" name="stats_${SET}_${kind}_cw" run_name="seed$seed" seed="$seed" out="$run" \
      model.contact_weight="$WEIGHT" model.contact_reach="$REACH" trainer.max_epochs="$EPOCHS" \
      trainer.enable_progress_bar=false "${resume[@]}"
  done
  ckpts=$(for seed in $SEEDS; do printf '%s,' "$OUT/seg_${kind}_cw${WEIGHT}_$seed/checkpoints/last.ckpt"; done)
  [ -f "$OUT/eval_${kind}_cw${WEIGHT}/results.csv" ] || \
    python -m drgan.evaluate data="$DATA" out="$OUT/eval_${kind}_cw${WEIGHT}" "models=[${ckpts%,}]"
done
