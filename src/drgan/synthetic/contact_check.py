"""Whether the generated scenes' touching particles show their contact as the real images' do (`generate`'s
contact_check.json).

A segmenter cuts two touching particles apart only where the image shows a neck (drgan.data.necks: the contact's
grey on the particles' scale; a ``hidden`` contact looks like the particles themselves). It learns from the generated
pairs and is checked on more of them (drgan.segmenters.closed_loop), so a generated set whose contacts hide their
neck more often than the user's images do trains on cuts it cannot see and reports more merges than the real images
will show (piled scenes in transmission hide many more contacts than the real images do). The real side is measured
on drgan's classical segmentation of the train patches (the patch set's settings, as the edge check:
drgan.synthetic.edge_check), the generated side on its exact labels, and compared (``hidden_difference``): the
classical contacts hide their neck about as often as annotated ones, while on generated pairs the classical
segmentation misses most hidden contacts (piled particles that overlap in projection show no neck of shape either,
so it merges them), which would hide the difference; the classical measurement of the generated images is kept
beside it (``generated``). Measured: experiments/statistics/closed_loop.md, "Merges where the image shows no neck:
tio2_tsem's closed loop".
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

WARN_HIDDEN = 0.15  # generated contacts hidden this much more often than the real ones are named
# Fewer real contacts than this say nothing about how often they hide their neck (a few large particles: a share of
# one or two contacts)
MIN_REAL_CONTACTS = 10


def classical_contacts(images, params, polarity: str) -> dict | None:
    """drgan.data.necks.contact_statistics of ``images`` segmented by drgan's classical method with ``params``."""
    from drgan.data.measurements import segment_image
    from drgan.data.necks import contact_statistics

    found = [segment_image(np.asarray(image, np.float32), params, polarity).labels for image in images]
    return contact_statistics([np.asarray(image, np.float64) for image in images], found)


def check_dataset(root, manifest: dict, backgrounds, polarity: str, resolution: int) -> dict | None:
    """The contact check of a complete generated set against the real train patches of ``backgrounds`` (as
    drgan.synthetic.noise_check.sample_sides gives them; None without real patches)."""
    from drgan.data.necks import contact_statistics
    from drgan.synthetic.noise_check import sample_sides

    sides = sample_sides(root, manifest, backgrounds, polarity, resolution)
    if sides is None:
        return None
    seen, params, images, labels = sides
    real = classical_contacts(list(np.asarray(seen, np.float64)), params, polarity)
    generated = classical_contacts(images, params, polarity)
    exact = contact_statistics(images, [np.asarray(label, np.int64) for label in labels])
    return {
        "real": real,
        "generated": generated,
        "generated_exact": exact,
        "hidden_difference": hidden_difference(real, exact),
        "polarity": polarity,
        "images": {"generated": len(images), "real": len(seen)},
    }


def hidden_difference(real: dict | None, exact: dict | None) -> float | None:
    """How much more often the generated contacts (exact labels) hide their neck than the real ones (classical
    segmentation); None without contacts on either side or with fewer than MIN_REAL_CONTACTS real ones."""
    if real is None or exact is None or real["contacts"] < MIN_REAL_CONTACTS:
        return None
    return round(exact["hidden"] - real["hidden"], 3)


def summary_line(result: dict) -> str:
    real, generated, exact = (result.get(k) or {} for k in ("real", "generated", "generated_exact"))

    def share(side):
        return "n/a" if side.get("hidden") is None else f"{side['hidden']:.0%}"

    few = real.get("contacts") is not None and real["contacts"] < MIN_REAL_CONTACTS
    return (
        f"contacts whose neck the image hides (neck grey >= 0.97): generated {share(exact)} (exact labels), real "
        f"{share(real)} (classical segmentation; of the generated images {share(generated)})"
        + (f"; {real['contacts']} real contacts are too few to compare (at least {MIN_REAL_CONTACTS})" if few else "")
    )


def log_result(result: dict) -> None:
    """The summary line, as a warning when the generated contacts hide their neck WARN_HIDDEN more often."""
    difference = result.get("hidden_difference")
    if difference is not None and difference > WARN_HIDDEN:
        log.warning(
            "%s: touching particles of the generated scenes show no neck more often than yours, so a segmenter trained "
            "on them learns other cuts than your images need and its closed-loop check is not theirs (%s)",
            summary_line(result), CAUSES.get(result.get("polarity"), CAUSES["dark"]),
        )  # fmt: skip
    else:
        log.info("%s", summary_line(result))


CAUSES = {  # what makes generated contacts hide their neck, by the particles' polarity
    "dark": "in transmission a particle piled over another hides their contact: placement.max_height and "
    "placement.min_distance_factor set the piling",
    "bright": "rendered secondary-electron contacts shine as bright as the particles where real ones often dip: "
    "material.imaging.recapture darkens them",
}
