"""``model.contact_weight=auto``: the contact weight a segmenter trained on a generated set takes, from what the set's
manifest says of the real particles: their polarity, and their arrangement (the Clark-Evans ratio of the particle
centroids, which drgan.profile measures and writes into the material as ``material.clark_evans``).

The weight (drgan.segmenters.module.contact_pixels) makes a U-Net separate touching particles; it pays where real
contacts merge (bright agglomerates in SEM) and costs AP50 where they do not (transmission images; bright spheres
packed side by side): experiments/pipeline/README.md, "Contact weight 10 against 0 on each set" and
"A contact-weight rule from the particles' arrangement".
"""

from __future__ import annotations

# The weight of each polarity; bright particles not clustered (Clark-Evans >= CLUSTERED_BELOW) take 0. A material
# without a measured arrangement (written by hand) goes by polarity alone.
CONTACT_WEIGHT_AUTO = {"bright": 10.0, "dark": 0.0}
CLUSTERED_BELOW = 1.0  # Clark-Evans ratio: < 1 clustered, 1 random (Poisson), > 1 regular


def resolve_contact_weight(value, polarity: str | None, clark_evans: float | None = None) -> tuple[float, str]:
    """``model.contact_weight`` as a number, and why: ``auto`` takes CONTACT_WEIGHT_AUTO's value for the generated
    set's polarity (0 without one: real images, hand-made pairs), and 0 for bright particles whose measured
    arrangement (``clark_evans``, the material's; None: not measured) is not clustered; a number stays (checked by
    the segmenter)."""
    if value != "auto":
        return value, "set"
    if polarity is None:
        return 0.0, "auto: 0, the pairs name no particle polarity (real images or hand-made pairs)"
    if polarity == "dark":
        why = "dark particles (transmission): every pixel alike, the weight cost AP50 on TEM sets"
        return CONTACT_WEIGHT_AUTO["dark"], f"auto: {CONTACT_WEIGHT_AUTO['dark']:g}, {why}"
    if clark_evans is not None and clark_evans >= CLUSTERED_BELOW:
        return 0.0, (
            f"auto: 0, bright particles arranged at random or regularly (Clark-Evans {clark_evans:g} >= "
            f"{CLUSTERED_BELOW:g}): every pixel alike, the weight split packed spheres that do not merge"
        )
    weight = CONTACT_WEIGHT_AUTO["bright"]
    arrangement = "arrangement not measured" if clark_evans is None else f"clustered, Clark-Evans {clark_evans:g}"
    return weight, (
        f"auto: {weight:g}, bright particles ({arrangement}): the pixels between touching particles weigh "
        f"{1 + weight:g} x, against merged agglomerates"
    )
