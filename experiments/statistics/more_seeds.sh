#!/usr/bin/env bash
# Two more U-Nets on a pipeline run's generated pairs, as the pipeline trains its own (the agreement check against the
# run's profile labels included), each scored on the set's test ids; then the seed table:
#
#     bash experiments/statistics/more_seeds.sh RUN DATASET OUT [SEEDS [OVERRIDE ...]]   # SEEDS default "2 4"
#     python experiments/statistics/seed_table.py SET RUN/segment:RUN/evaluate OUT/seg_2:OUT/ev_2 OUT/seg_4:OUT/ev_4
#
# Seeds 2 and 4, not 1 and 2: a weak seed is retried with seed + 1 (drgan.segmenters.agreement), so neighbouring
# seeds could train the same network twice. Set PYTHONPATH to a worktree to run frozen code beside edits.
set -eu
RUN=$1; DATASET=$2; OUT=$3; SEEDS=${4:-"2 4"}
shift $(( $# < 4 ? $# : 4 ))  # the rest: segment overrides (e.g. model.lr_schedule=poly)
mkdir -p "$OUT"
for s in $SEEDS; do
    python -m drgan.segment data="$RUN/generate" out="$OUT/seg_$s" name=seeds run_name="seg_$s" seed="$s" logger=none \
        agreement.images="$DATASET/images" agreement.reference="$RUN/profile/labels" \
        trainer.enable_progress_bar=false "$@" > "$OUT/seg_$s.log" 2>&1
    python -m drgan.evaluate model="$OUT/seg_$s/checkpoints/last.ckpt" data="$DATASET" out="$OUT/ev_$s" > "$OUT/ev_$s.log" 2>&1
done
