"""The particle scale (and neck depth) patch mining would search for an experiment's train images, measured as
`drgan.train` measures it (the datamodule's own images, crop and polarity; no patches mined), to be written into the
experiment's ``data.segment`` so that each training skips the search (~1 min per image on the 2-core CPU).

    python experiments/profile/pin_scale.py tio2_sem tio2_tsem
"""

from __future__ import annotations

import argparse
import time

from hydra.utils import instantiate

from drgan.launch.configs import compose


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiments", nargs="+")
    for name in parser.parse_args().experiments:
        cfg = compose([f"experiment={name}", "logger=none", "data.cache_dir=null"], config_name="train")
        dm = instantiate(cfg.data, resolution=int(cfg.renderer.resolution))
        t = time.perf_counter()
        # the scale and neck depth the experiment sets are what is measured again: searched as if unset
        params, estimate, searched = dm.search_segment()
        seconds = time.perf_counter() - t
        print(f"{name}: {len(searched)} train images searched ({', '.join(searched)}), {dm.polarity} particles, "
              f"{seconds:.0f} s")  # fmt: skip
        print(f"  resolved: {params.as_dict()}")
        print(f"  estimate: {estimate.as_dict() if estimate else None}")
        print(
            f"  pin: data.segment.scale={params.scale} data.segment.neck_depth={params.neck_depth} "
            f"data.segment.min_separability={params.min_separability}"
        )


if __name__ == "__main__":
    main()
