"""The real-count guard (drgan.segmenters.calibrate.real_count_guard) applied to a finished segment run's stored
calibration, as drgan.segment now applies it after training: prints the counts and the split it would store.

    python experiments/statistics/real_count_guard.py PIPELINE_RUN IMAGES [REFERENCE_LABELS [SEGMENT_RUN]]

REFERENCE_LABELS defaults to PIPELINE_RUN/profile/labels, SEGMENT_RUN to PIPELINE_RUN/segment.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from omegaconf import OmegaConf

from drgan.segmenters.agreement import agreement_settings, read_reference
from drgan.segmenters.calibrate import real_count_guard
from drgan.segmenters.registry import load_segmenter


def main() -> None:
    run, images = Path(sys.argv[1]), sys.argv[2]
    reference = sys.argv[3] if len(sys.argv) > 3 else str(run / "profile" / "labels")
    segment = Path(sys.argv[4]) if len(sys.argv) > 4 else run / "segment"
    calibration = json.loads((segment / "metrics.json").read_text())["split_calibration"]
    before = (calibration.get("real_count") or {}).get("from")
    if before:  # a run the guard already moved: start again from the validation pairs' own choice
        row = next(r for r in calibration["table"] if all(r[k] == v for k, v in before.items()))
        calibration = {**calibration, **{k: row[k] for k in (*before, "ap50", "median_error", "count_error")}}
    items = read_reference(agreement_settings(OmegaConf.create({"images": images, "reference": reference})))
    guarded = real_count_guard(load_segmenter(segment / "checkpoints" / "last.ckpt"), calibration, items)
    chosen = {k: guarded[k] for k in ("split_seeds", "split_depth", "split_core", "ap50")}
    print(f"{segment}: {guarded.get('real_count')}\n  stored split: {chosen}")


if __name__ == "__main__":
    main()
