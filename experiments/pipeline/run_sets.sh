#!/usr/bin/env bash
# Issue 50's end-to-end measurement: `drgan.pipeline` on each data set with nothing set by hand but the folders.
#
#   bash experiments/pipeline/run_sets.sh tio2_tsem cej ...      # one after the other; rerun to resume
#
# tio2_sem / tio2_tsem: the shared BAM sets (train ids in, test ids scored). EMPS groups (cej, actbio, apsusc,
# saa890): one paper's images each, prepared by experiments/pipeline/emps_groups.py under $EMPS_GROUPS (default
# /work/data/emps: symlinks to ../shared, never copies in the repository) with a split fixed before any run.
# Each run is named after its set, with "bam_" before the BAM sets' names (tio2_sem and tio2_tsem are also the names of
# materials drgan ships, which a run's material may not take): runs/pipeline/<name>, its console output
# runs/pipeline/<name>.log.
set -euo pipefail
DATA=${DRGAN_DATA:-../shared/datasets}
GROUPS_DIR=${EMPS_GROUPS:-/work/data/emps}
mkdir -p runs/pipeline
for set in "$@"; do
  case $set in
    tio2_sem|tio2_tsem) dir=$DATA/$set; name=bam_$set ;;
    *) dir=$GROUPS_DIR/$set; name=$set ;;
  esac
  echo "=== $name ($(date -u +%H:%M:%S))"
  python -m drgan.pipeline data.dir="$dir/images" name="$name" annotated="$dir" >>"runs/pipeline/$name.log" 2>&1 ||
    echo "$name failed: see runs/pipeline/$name.log"
done
