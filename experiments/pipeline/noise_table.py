"""The fine-noise check (drgan.synthetic.noise_check) of finished pipeline runs, as a markdown table: what
`drgan.generate` now writes to noise_check.json, computed for runs generated before it did.

    python experiments/pipeline/noise_table.py runs/pipeline/bam_tio2_tsem runs/old/bam_tio2_sem_v1 ...

A run folder moved after it ran (runs/old/...) is read where it is now: its generate config's patch folder is taken
from the run folder itself (RUN/train/patches).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from drgan.synthetic.noise_check import check_dataset


def main(runs: list[str]) -> None:
    print("| run | background: real / generated | ratio | particles: real / generated | ratio |")
    print("|---|---|---|---|---|")
    for run in map(Path, runs):
        manifest = json.loads((run / "generate" / "manifest.json").read_text())
        config = manifest["config"]
        result = check_dataset(
            run / "generate", manifest, run / "train" / "patches", config["polarity"], config["renderer"]["resolution"]
        )
        cells = []
        for name in ("background", "particles"):
            row = result[name]
            cells += [f"{row['real']} / {row['generated']}", f"{row['ratio']} x"]
        print(f"| {run.name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
