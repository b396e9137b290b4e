#!/usr/bin/env bash
# The split calibration's two objectives on the same segmenters: each run's stored split (the sizes objective, the
# default) and the AP50 objective's (recalibrated on the same validation pairs, no training), both scored on an
# annotated set's test ids. Prints one line per run and objective.
#
#   bash experiments/statistics/objectives.sh GENERATED DATASET RUN [RUN ...]
set -euo pipefail
GEN=${1:?usage: objectives.sh GENERATED DATASET RUN...}
DATA=${2:?usage: objectives.sh GENERATED DATASET RUN...}
shift 2
for R in "$@"; do
  line=$(python experiments/pipeline/recalibrate.py "$R" --generated "$GEN" --objective ap50 2>/dev/null | grep "^{'split'")
  read -r depth core seeds < <(python -c "import ast,sys; c=ast.literal_eval(sys.argv[1]); print(c['split_depth'], 'null' if c['split_core'] is None else c['split_core'], c['split_seeds'])" "$line")
  python -m drgan.evaluate model="$R/checkpoints/last.ckpt" data="$DATA" out="$R/ev_ap50" bootstrap=200 overlays=false \
    inference.split_depth="$depth" inference.split_core="$core" inference.split_seeds="$seeds" > "$R/ev_ap50.log" 2>&1
  python -m drgan.evaluate model="$R/checkpoints/last.ckpt" data="$DATA" out="$R/ev_sizes" bootstrap=200 overlays=false \
    > "$R/ev_sizes.log" 2>&1
  for v in ap50 sizes; do
    echo "$R $v: DSC/AP50 $(sed -n 10p "$R/ev_$v/results.md" | cut -d'|' -f3,4) median/count/KS $(grep '^| run0' "$R/ev_$v/statistics.md" | head -1 | cut -d'|' -f4,6,8)"
  done
done
