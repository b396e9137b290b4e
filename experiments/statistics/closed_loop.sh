#!/usr/bin/env bash
# Segmenter variants on one generated set, each scored by its own closed-loop check (held-out pairs, exact truth);
# resumable (a finished run is skipped). Prints the table of experiments/statistics/closed_loop_table.py.
#
#   VARIANTS="default ce_only" SEEDS="0" EPOCHS=12 bash experiments/statistics/closed_loop.sh GENERATED OUT [args...]
#
# Variants: default (drgan.segment's defaults), ce_only (model.dice_weight=0), and any NAME=override,override.
set -euo pipefail
DATA=$(cd "${1:?usage: closed_loop.sh GENERATED OUT [segment args...]}" && pwd)
OUT=${2:?usage: closed_loop.sh GENERATED OUT}
shift 2
mkdir -p "$OUT"
export OMP_NUM_THREADS=${THREADS:-2}
for variant in ${VARIANTS:-default}; do
  case $variant in
    default) name=default; args=() ;;
    ce_only) name=ce_only; args=(model.dice_weight=0) ;;
    *=*) name=${variant%%=*}; IFS=, read -r -a args <<<"${variant#*=}" ;;
    *) echo "closed_loop.sh: unknown variant $variant" >&2; exit 2 ;;
  esac
  for seed in ${SEEDS:-0}; do
    run=$OUT/${name}_$seed
    [ -f "$run/metrics.json" ] && continue
    resume=(); [ -f "$run/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
    python -m drgan.segment data="$DATA" name=closed_loop run_name="${name}_$seed" seed="$seed" out="$run" \
      logger=none trainer.enable_progress_bar=false trainer.max_epochs="${EPOCHS:-12}" "${args[@]}" "$@" \
      "${resume[@]}" > "$run.log" 2>&1 || echo "$run failed: see $run.log"
  done
done
python experiments/statistics/closed_loop_table.py "$OUT"/*/metrics.json
