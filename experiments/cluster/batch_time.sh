#!/usr/bin/env bash
# The two-sample batch on SLURM against the same two pipelines one after the other, locally, with sacct of the SLURM
# run (experiments/cluster/README.md). Tiny renders (benchmarks/pipeline.py's TINY): the scheduler's plumbing and
# overheads, not the stages' real cost.
#   sudo bash scripts/slurm_local.sh --accounting && bash experiments/cluster/batch_time.sh /work/tmp/cluster
set -euo pipefail
OUT=${1:?usage: batch_time.sh OUT}
cd "$(dirname "$0")/../.."
rm -rf "$OUT" && mkdir -p "$OUT"
TINY=$(python -c "
import importlib.util
spec = importlib.util.spec_from_file_location('b', 'benchmarks/pipeline.py'); m = importlib.util.module_from_spec(spec)
spec.loader.exec_module(m); print(' '.join(m.TINY))")
python - "$OUT" <<'PY'
import importlib.util, sys
from pathlib import Path
spec = importlib.util.spec_from_file_location("b", "benchmarks/pipeline.py"); m = importlib.util.module_from_spec(spec)
spec.loader.exec_module(m)
out = Path(sys.argv[1])
m.tiny_set(out / "set_a", seed=0)
m.tiny_set(out / "set_b", seed=0, n_train=3)
(out / "samples.csv").write_text(f"name,dir,annotated\na,{out}/set_a/images,{out}/set_a\nb,{out}/set_b/images,{out}/set_b\n")
PY
SMALL="slurm.gpus=0 slurm.cpus=1 slurm.mem=2G slurm.time=30"
export MLFLOW_TRACKING_URI="sqlite:///$OUT/mlflow.db"

start=$(date +%s.%N)
since=$(date +%Y-%m-%dT%H:%M:%S)
python -m drgan.pipeline batch="$OUT/samples.csv" out="$OUT/slurm" launcher=slurm $SMALL $TINY
while [[ ! -f "$OUT/slurm/summary.md" ]]; do sleep 1; done
slurm_s=$(python -c "print(round($(date +%s.%N) - $start))")

start=$(date +%s.%N)
python -m drgan.pipeline batch="$OUT/samples.csv" out="$OUT/local" progress=0 $TINY > "$OUT/local.log" 2>&1
local_s=$(python -c "print(round($(date +%s.%N) - $start))")

echo
echo "| run | wall s |"
echo "|---|---|"
echo "| two samples, SLURM batch (submission to summary) | $slurm_s |"
echo "| the same two, locally one after the other | $local_s |"
echo
if command -v sacct >/dev/null && sacct -n -X -S "$since" >/dev/null 2>&1; then
    sacct -X -S "$since" -o JobID%8,JobName%22,State,Start,End,Elapsed,ExitCode
else
    echo "(no sacct here: start SLURM with scripts/slurm_local.sh --accounting for the job table)"
fi
