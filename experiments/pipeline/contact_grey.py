"""What does a contact between two touching particles look like, in generated pairs and in real annotated images?

Issue 51: touching tio2_sem particles stay merged after the split, in generated-trained segmenters more than in the
real-trained one. A segmenter can only learn to cut where the training images show a cue. For every pair of touching
instances (generated: the exact labels; real: the annotation's instances, which a 1 px line separates), the ridge
is the pixels with both particles within 1 px (3 x 3 window); its grey is put on the particles' own scale:

    neck = (median ridge grey - background grey) / (median core grey of the two - background grey)

1: the contact is as bright (dark) as the particles, no cue; 0: it falls to the background, a gap anyone can cut;
> 1: a line brighter than the particles (an SEM edge). Core: instance pixels with no other label within 2 px;
background: pixels with no particle within 3 px (the image's median). Prints the quartiles of ``neck`` and the
share of contacts below 0.5 (a visible gap) and above 1.1 (a bright line), per set. Also each contact's width
relative to the smaller particle of the two (the ridge's extent along its principal axis, sqrt(12 var), over the
smaller equivalent diameter): near 0 a point contact, near 1 a neck as wide as the particle (two particles that
look like one).

    python experiments/pipeline/contact_grey.py --generated runs/pipeline/bam_tio2_sem/generate \
        --real ../shared/datasets/tio2_sem --ids train
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from edge_offset import generated_images, real_images  # beside this script

from drgan.data.necks import contact_counts, necks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generated", type=Path)
    parser.add_argument("--real", type=Path)
    parser.add_argument("--ids", default="train")
    parser.add_argument("--n", type=int, default=200)
    args = parser.parse_args()
    print(
        "| pairs | contacts | neck grey: quartiles (1 = as the particles, 0 = background) | gap (< 0.5) | line (> 1.1) "
        "| neck width / smaller diameter: quartiles | wide (> 0.7) | contacts per particle (not cut by the border) "
        "| particles touching |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, values in (
        (f"generated ({args.generated})", generated_images(args.generated, args.n) if args.generated else None),
        (f"real masks, {args.ids} ids ({args.real})", real_images(args.real, args.ids) if args.real else None),
    ):
        if values is not None:
            values = list(values)
            v, w = np.asarray([(n.grey, n.width) for image, labels in values for n in necks(image, labels)]).T
            n, contacts, touching = np.sum([contact_counts(labels) for _, labels in values], axis=0)
            q, r = np.percentile(v, [25, 50, 75]), np.percentile(w, [25, 50, 75])
            print(f"| {name} | {len(v)} | {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} | {np.mean(v < 0.5):.0%} | "
                  f"{np.mean(v > 1.1):.0%} | {r[0]:.2f} / {r[1]:.2f} / {r[2]:.2f} | {np.mean(w > 0.7):.0%} | "
                  f"{contacts / n:.2f} | {touching / n:.0%} |")  # fmt: skip


if __name__ == "__main__":
    main()
