"""The particle scale (and neck depth) patch mining would search for an experiment's train images, measured as
`drgan.train` measures it (the datamodule's own images, crop and polarity; no patches mined), to be written into the
experiment's ``data.segment`` so that each training skips the search (~1 min per image on the 2-core CPU).

    python experiments/profile/pin_scale.py tio2_sem tio2_tsem
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from hydra.utils import instantiate

from drgan.configs import compose
from drgan.data.images import read_grey
from drgan.data.particles import SegmentParams, resolve_params
from drgan.data.patches import scale_sample


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiments", nargs="+")
    for name in parser.parse_args().experiments:
        cfg = compose([f"experiment={name}", "logger=none", "data.cache_dir=null"], config_name="train")
        dm = instantiate(cfg.data, resolution=int(cfg.renderer.resolution))
        paths, ids, _ = dm.resolve_ids()
        images = [read_grey(p, dm.crop_rows) for p in paths]
        dm.resolve_polarity(images)
        sample = scale_sample(images)  # as mine_patches samples them
        t = time.perf_counter()
        # the scale and neck depth the experiment sets are what is measured again: searched as if unset
        unset = replace(SegmentParams.from_config(dm.segment), scale=None, neck_depth=None)
        params, estimate = resolve_params(sample, unset, dm.polarity)
        seconds = time.perf_counter() - t
        print(
            f"{name}: {len(ids)} train images, {len(sample)} searched ({', '.join(scale_sample(ids))}), "
            f"{dm.polarity} particles, {seconds:.0f} s"
        )
        print(f"  resolved: {params.as_dict()}")
        print(f"  estimate: {estimate.as_dict() if estimate else None}")
        print(
            f"  pin: data.segment.scale={params.scale} data.segment.neck_depth={params.neck_depth} "
            f"data.segment.min_separability={params.min_separability}"
        )


if __name__ == "__main__":
    main()
