"""Does filling a particle's holes (inference.fill_holes) move the closed-loop check? A segment run's check pairs
(the ids its checkpoint's check lists) predicted with its calibrated split, holes filled and not.

    python experiments/statistics/fill_holes.py SEGMENT_RUN GENERATED_SET

Prints one markdown row per setting: median / count error, edge offset, merged, AP50. The real images' side:
`python -m drgan.evaluate model=... data=DATASET subset=train inference.fill_holes=true|false`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from drgan.segmenters.closed_loop import check_inference, closed_loop
from drgan.segmenters.inference import predict
from drgan.segmenters.pairs import load_generated_pairs
from drgan.segmenters.registry import load_segmenter


def main() -> None:
    run, data = Path(sys.argv[1]), Path(sys.argv[2])
    model = load_segmenter(run / "checkpoints" / "last.ckpt")
    ids = set(model.closed_loop["ids"])
    pairs = [p for p in load_generated_pairs(data) if str(p.id) in ids]
    settings = check_inference(model.split_calibration)
    print("| fill_holes | pairs | median error | count error | edge offset px | merged | AP50 |")
    print("|---|---|---|---|---|---|---|")
    for fill in (False, True):

        def predictor(image, fill=fill):
            return predict(model, image, pixel_scale=1.0, noise_match=False, annotations=False, fill_holes=fill,
                           **settings)  # fmt: skip

        c = closed_loop(model, pairs, model.split_calibration, predictor=predictor)
        print(f"| {fill} | {len(pairs)} | {c['median_error']['value']:+.3f} | {c['count_error']['value']:+.3f} | "
              f"{c['edge_offset_px']:+.2f} | {c['merged']:.3f} | {c['ap50']:.3f} |")  # fmt: skip


if __name__ == "__main__":
    main()
