#!/usr/bin/env bash
# drgan's first run on a lent GPU (../shared/gpu/README.md): one command through the device tool, every step with a
# time limit of its own so that one hang cannot eat the session's device time, every log under $OUT.
#   carry: .gpu_site.tar.xz (bash ../shared/gpu/build_site.sh), .gpu_wheels (pytest's wheels: the GPU machine has
#          no pytest), .gpu_data/tio2_sem/images (a few *train* images of tio2_sem; never a test id)
#   command: bash experiments/gpu/check.sh [STEPS]     STEPS: any of "variant tests bench train generate genbench ddp"
# Results and what they mean: experiments/gpu/README.md.
set -uo pipefail
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
steps=${1:-variant tests bench train generate}
t0=$(date +%s)
log() { echo "[$(($(date +%s) - t0)) s] $*" | tee -a "$OUT/steps.txt"; }

tar -xJf .gpu_site.tar.xz -C /tmp
python3 -c "import pytest" 2>/dev/null || for w in .gpu_wheels/*.whl; do python3 -m zipfile -e "$w" /tmp/.gpu_site; done
export PYTHONPATH=/tmp/.gpu_site:$PWD/src DRGAN_DATA=$PWD/.gpu_data DRGAN_ROOT=/tmp/drgan_root
mkdir -p /tmp/drgan_root
log "site unpacked"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$OUT/nvidia_smi.csv" 2>&1
python3 -c "import torch, sys; print(sys.version.split()[0], torch.__version__, torch.cuda.is_available())" \
  > "$OUT/python.txt" 2>&1

run() {  # run NAME SECONDS CMD...: the command's stdout+stderr in $OUT/NAME.log, its exit status in steps.txt
  local name=$1 limit=$2
  shift 2
  log "$name: start (limit $limit s)"
  timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
  log "$name: exit $?"
}

FID_EXTRACTOR='callbacks.fid.extractor={_target_:drgan.callbacks.RandomProjectionFeatures,dim:64}'

for step in $steps; do
  case $step in
  variant)
    run variant 60 python3 -c "
import time; t = time.time()
import mitsuba as mi; mi.set_variant('cuda_ad_rgb'); print('mitsuba', mi.__version__, mi.variant(), f'{time.time() - t:.1f} s')
from drgan.core import backend; print('drgan auto ->', backend.resolve_variant('auto'), 'use_variant ->', backend.use_variant('auto'))
" ;;
  tests)  # the render and gradient tests (finite differences included) on cuda_ad_rgb
    DRGAN_TEST_VARIANT=cuda_ad_rgb run tests ${TESTS_LIMIT:-150} python3 -m pytest -v -p no:cacheprovider --durations=15 \
      tests/test_scene.py tests/test_direct_integrator.py tests/test_grad_seed.py tests/test_transmission.py \
      tests/test_fringe.py tests/test_stability.py ;;
  bench)
    run bench 90 python3 benchmarks/train_step.py --spp 16 121 --fid-images 0 --steps 5 --warmup 2 ;;
  train)  # two short epochs on 6 train images: iterations per second under Lightning, FID by random projections
    run train ${TRAIN_LIMIT:-150} python3 -m drgan.train experiment=tio2_sem logger=none data.split=null \
      trainer.max_epochs=${TRAIN_EPOCHS:-2} trainer.limit_train_batches=20 "$FID_EXTRACTOR" ${TRAIN_ARGS:-} \
      callbacks.early_stopping.max_minutes=2 paths.log_dir=/tmp/runs run_name=gpu
    ckpt=$(ls /tmp/runs/tio2_sem/gpu/checkpoints/best.ckpt 2>/dev/null)
    [ -n "$ckpt" ] && cp "$ckpt" "$OUT/best.ckpt" && log "best.ckpt $(du -k "$ckpt" | cut -f1) kB" ;;
  generate)  # 1000 pairs from that checkpoint (seed 0): images per second; the first 8 come back for a CPU comparison
    run generate 60 python3 -m drgan.generate ckpt=/tmp/runs/tio2_sem/gpu n=1000 out=/tmp/gen n_background=0 \
      progress=false
    log "generated $(ls /tmp/gen/images 2>/dev/null | wc -l) images"
    mkdir -p "$OUT/gen" && for f in $(ls /tmp/gen/images 2>/dev/null | sort | head -8); do cp "/tmp/gen/images/$f" "$OUT/gen/"; done
    cp /tmp/gen/manifest.json "$OUT/gen/" 2>/dev/null ;;
  genbench)  # benchmarks/generate.py: pairs per minute by spp and resolution, render and labels apart
    run genbench ${GENBENCH_LIMIT:-120} python3 benchmarks/generate.py --spp 16 121 --resolution 256 512 --images 20 ;;
  ddp)
    run ddp ${DDP_LIMIT:-120} python3 -m drgan.train experiment=tio2_sem logger=none data.split=null trainer=ddp trainer.devices=1 \
      trainer.max_epochs=1 trainer.limit_train_batches=5 "$FID_EXTRACTOR" ${TRAIN_ARGS:-} paths.log_dir=/tmp/runs run_name=gpu_ddp ;;
  esac
done
log "done"
