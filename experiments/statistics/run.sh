#!/usr/bin/env bash
# Issue 27's rows for one data set, end to end, every step resumable (rerun the same command to continue):
#
#   bash experiments/statistics/run.sh tio2_sem|tio2_tsem [OUT]
#
# 1. the GAN with the recorded experiment (`experiment=SET`, stops by itself within ~27 minutes on 2 cores),
#    trained on the train ids only;
# 2. 1,000 generated pairs (spp 16) + 200 real background patches from the train ids;
# 3. U-Nets, 3 seeds each: on the generated pairs (synthetic-trained) and on the real train images
#    (real-trained, area-based epochs), at most 12 epochs with early stopping on the validation loss;
# 4. drgan.evaluate of each group on the 8 test ids (DSC, AP50, PQ and the particle statistics).
# Outputs under OUT (default runs/statistics/SET); nothing of it is committed (the real images are licensed
# no-derivatives). SEEDS="0" for a single seed; KINDS=synthetic for the synthetic-trained alone; MINUTES=12 for a shorter GAN; STEPS="gan generate segment evaluate" to run a part.
set -euo pipefail
SET=${1:?usage: run.sh tio2_sem|tio2_tsem [OUT]}
OUT=${2:-runs/statistics/$SET}
DATA=${DRGAN_DATA:-../shared/datasets}/$SET
SEEDS=${SEEDS:-0 1 2}
STEPS=${STEPS:-gan generate segment evaluate}
KINDS=${KINDS:-synthetic real}   # which U-Nets: on the generated pairs, on the real train images
EPOCHS=${EPOCHS:-12}
MINUTES=${MINUTES:-27}   # the GAN's wall-clock budget
GAN=$OUT/gan
case $SET in
  tio2_sem) CONTOUR=1; GAN_ARGS=(callbacks.early_stopping.max_minutes=$MINUTES) ;;
  # tio2_tsem's experiment has no budget of its own: the same 27 minutes and ~half the patches per epoch as tio2_sem
  tio2_tsem) CONTOUR=1; GAN_ARGS=(trainer.limit_train_batches=63 callbacks.early_stopping.max_minutes=$MINUTES) ;;
  *) echo "run.sh: unknown data set $SET (expected tio2_sem or tio2_tsem)" >&2; exit 2 ;;
esac
mkdir -p "$OUT"
has() { [[ " $STEPS " == *" $1 "* ]]; }

if has gan && [ ! -f "$GAN/checkpoints/best.ckpt" ]; then
  resume=(); [ -f "$GAN/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
  python -m drgan.train experiment="$SET" hydra.run.dir="$GAN" "${GAN_ARGS[@]}" "${resume[@]}"
fi
if has generate; then
  python -m drgan.generate ckpt="$GAN" n=1000 n_background=200 out="$OUT/synthetic" renderer.spp=16 progress=false
fi
if has segment; then
  for seed in $SEEDS; do
    for kind in $KINDS; do
      run=$OUT/seg_${kind}_$seed
      [ -f "$run/metrics.json" ] && continue
      resume=(); [ -f "$run/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
      if [ $kind = synthetic ]; then src=(data="$OUT/synthetic"); else src=(real="$DATA" contour_px=$CONTOUR); fi
      python -m drgan.segment "${src[@]}" name="stats_${SET}_$kind" run_name=seed$seed seed=$seed out="$run" \
        trainer.max_epochs=$EPOCHS trainer.enable_progress_bar=false "${resume[@]}"
    done
  done
fi
if has evaluate; then
  for kind in $KINDS; do
    ckpts=$(for seed in $SEEDS; do printf '%s,' "$OUT/seg_${kind}_$seed/checkpoints/last.ckpt"; done)
    python -m drgan.evaluate data="$DATA" out="$OUT/eval_$kind" "models=[${ckpts%,}]"
  done
  python -m drgan.evaluate data="$DATA" model=classical out="$OUT/eval_classical"
fi
