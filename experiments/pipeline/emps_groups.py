"""EMPS paper groups as annotated datasets for drgan.pipeline: OUT/<group>/images, masks (symlinks to the shared
images and instance maps: nothing copied, nothing in the repository) and split.json. Also OUT/tsem4: a small
dark-particle set, the first 4 train ids of tio2_tsem (its 8 test ids to score), for the GAN on few patches.

    python experiments/pipeline/emps_groups.py [--out /work/data/emps]

The split was fixed before any run: the group's ids sorted, every third (starting with the first) is a test id. The
test ids are scored at the end of the pipeline (annotated=OUT/<group>); the train ids are the unannotated folder the
pipeline profiles and trains on (data.dir=OUT/<group>/images, whose ../split.json names them).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
from pathlib import Path

EMPS = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "emps_train"
GROUPS = {  # name: DOI of the paper (sources.csv); 5-12 images each
    "cej": "10.1016.j.cej.2019.122990",  # 6 SEM images: bright rods and spheres on a dark stage, scale bars
    "actbio": "10.1016.j.actbio.2020.04.055",  # 6 TEM images: dark rings on a grainy film (and two single vesicles)
    "apsusc": "10.1016.j.apsusc.2020.145360",  # 12 SEM images: large bright spheres, densely packed
    "saa890": "10.1016.j.saa.2019.117890",  # 8 TEM images: dark flakes and particles of many sizes
    # 5 images of two kinds: SEM of single spheres filling the frame (bright) and TEM of dark round particles;
    # its train ids hold two of the SEM ones and one TEM: the profile takes them for bright particles, and no single
    # material fits them (a mixed folder, not a set to measure the pipeline on)
    "saa177": "10.1016.j.saa.2019.117177",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/work/data/emps"))
    args = parser.parse_args()
    rows = list(csv.DictReader((EMPS / "sources.csv").open()))
    for name, doi in GROUPS.items():
        ids = sorted(r["id"] for r in rows if r["doi"] == doi)
        test = ids[::3]
        train = [i for i in ids if i not in test]
        folder = args.out / name
        for sub, source in (("images", "images"), ("masks", "instances")):
            (folder / sub).mkdir(parents=True, exist_ok=True)
            for i in ids:
                link = folder / sub / f"{i}.png"
                if not link.exists():
                    os.symlink(EMPS / source / f"{i}.png", link)
        (folder / "split.json").write_text(json.dumps({"train": train, "test": test}, indent=1))
        print(f"{name}: {len(train)} train, {len(test)} test {test}")
    tsem = EMPS.parent / "tio2_tsem"
    split = json.loads((tsem / "split.json").read_text())
    folder, train = args.out / "tsem4", split["train"][:4]
    for sub in ("images", "masks"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
        for i in train + split["test"]:
            link = folder / sub / f"{i}.tif"
            if not link.exists():
                os.symlink(tsem / sub / f"{i}.tif", link)
    (folder / "split.json").write_text(json.dumps({"train": train, "test": split["test"]}, indent=1))
    print(f"tsem4: {len(train)} train, {len(split['test'])} test")


if __name__ == "__main__":
    main()
