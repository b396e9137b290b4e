#!/usr/bin/env bash
# issue 67: each pipeline run re-analysed with its profile (analyze profile=), then its trusted sizes against the masks
# (train and test ids). The EMPS groups lie in /work/data/emps (experiments/pipeline/emps_groups.py makes them).
cd "$(dirname "$0")/../.."
for pair in tio2_sem_0:../shared/datasets/tio2_sem tio2_tsem_flat_0:../shared/datasets/tio2_tsem tsem4_0:/work/data/emps/tsem4 cej_0:/work/data/emps/cej apsusc_0:/work/data/emps/apsusc; do
  run=${pair%%:*}; data=${pair#*:}; R=runs/benchmarks/pipeline/$run
  P=$R/profile; [ $run = tio2_sem_0 ] && P=runs/sizes_half/tio2_sem/profile
  [ -f runs/trusted3/$run/summary.json ] || python -m drgan.analyze model=$R/segment/checkpoints/last.ckpt images=$data/images profile=$P out=runs/trusted3/$run > runs/trusted3/$run.log 2>&1
  for sub in train test; do python experiments/statistics/trusted_sizes.py runs/trusted3/$run $data --name $run --subset $sub; done
done
