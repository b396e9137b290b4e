#!/usr/bin/env bash
# Segmenters beside a finished drgan.pipeline run, on the same generated pairs, to choose the defaults (issue 50) and
# compare the instance-aware segmenter with the U-Net (issue 51); every run resumable (rerun the same command).
#
#   VARIANTS="unet centres" SEEDS="0 1 2" bash experiments/pipeline/segmenters.sh runs/pipeline/bam_tio2_tsem
#
# Variants (synthetic-trained on RUN/generate; real_* on the annotated set's train ids, its split.json):
#   unet        drgan.segment's defaults (the U-Net)          unet_z      the same with model.normalize=zscore
#   unet_c      the U-Net with model.contact_weight=10 (the pixels between touching particles weigh 11x)
#   tex         the U-Net with loader.texture=0.1 (a random surface texture on every training crop)
#   unet_0      the U-Net with model.contact_weight=0 (the default before contact_weight=auto; its seed 0 is the
#               pipeline's own segmenter for runs from before auto: link RUN/segment as RUN/extra/unet_0_0)
#   unet_w      the U-Net at the instance-aware segmenter's working scale (loader.working_px=40: pairs of larger
#               particles shrunk to a 40-px median particle, inference alike)
#   centres     the instance-aware CentreSegmenterModule      centres_z   the same with model.normalize=zscore
#   real_unet / real_centres   trained on the real annotated train images instead (contour 1 px, area-based epochs)
# Each variant's 3 seeds are scored together on the annotated test ids (drgan.evaluate models=[...]), and once the
# classical baseline. Everything goes under RUN/extra/ (runs/ is never committed). THREADS: torch threads per run.
set -euo pipefail
RUN=$(cd "${1:?usage: segmenters.sh RUN_FOLDER}" && pwd)
VARIANTS=${VARIANTS:-unet centres}
SEEDS=${SEEDS:-0 1 2}
ANNOTATED=$(python -c "import json,sys; print(json.load(open('$RUN/pipeline.json'))['annotated'])")
OUT=$RUN/extra
mkdir -p "$OUT"
export OMP_NUM_THREADS=${THREADS:-2}
centres=(model._target_=drgan.segmenters.instances.CentreSegmenterModule +model.distance_weight=5.0)

for variant in $VARIANTS; do
  case $variant in
    unet) args=(data="$RUN/generate") ;;
    unet_z) args=(data="$RUN/generate" model.normalize=zscore) ;;
    unet_c) args=(data="$RUN/generate" model.contact_weight=10) ;;
    unet_0) args=(data="$RUN/generate" model.contact_weight=0) ;;
    unet_w) args=(data="$RUN/generate" loader.working_px=40) ;;
    tex) args=(data="$RUN/generate" loader.texture=0.1) ;;
    centres) args=(data="$RUN/generate" "${centres[@]}") ;;
    centres_z) args=(data="$RUN/generate" "${centres[@]}" model.normalize=zscore) ;;
    real_unet) args=(real="$ANNOTATED" contour_px=1) ;;
    real_centres) args=(real="$ANNOTATED" contour_px=1 "${centres[@]}") ;;
    *) echo "segmenters.sh: unknown variant $variant" >&2; exit 2 ;;
  esac
  ckpts=()
  for seed in $SEEDS; do
    run=$OUT/${variant}_$seed
    ckpts+=("$run/checkpoints/last.ckpt")
    [ -f "$run/metrics.json" ] && continue
    resume=(); [ -f "$run/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
    python -m drgan.segment "${args[@]}" name="extra_$(basename "$RUN")" run_name="${variant}_$seed" seed="$seed" \
      out="$run" logger=none trainer.enable_progress_bar=false "${resume[@]}" > "$run.log" 2>&1
  done
  [ -f "$OUT/eval_$variant/statistics.md" ] ||
    python -m drgan.evaluate data="$ANNOTATED" out="$OUT/eval_$variant" "models=[$(IFS=,; echo "${ckpts[*]}")]" \
      > "$OUT/eval_$variant.log" 2>&1
done
[ -f "$OUT/eval_classical/statistics.md" ] ||
  python -m drgan.evaluate data="$ANNOTATED" model=classical out="$OUT/eval_classical" > "$OUT/eval_classical.log" 2>&1
echo "done: $OUT/eval_*/results.md and statistics.md"
