"""Contacts between touching particles and whether the image shows them (drgan.data.necks), and the generated
set's contact check against the real patches (drgan.synthetic.contact_check)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from drgan.data.necks import HIDDEN_NECK, contact_counts, contact_statistics, necks

BACKGROUND, PARTICLE = 0.8, 0.1


def two_touching_discs(size: int = 96, radius: int = 14) -> np.ndarray:
    """Labels: discs 1 and 2 side by side, touching along a vertical line at column size / 2; disc 3 alone."""
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    c = size // 2
    labels[(yy - 30) ** 2 + (xx - (c - radius)) ** 2 <= radius**2] = 1
    labels[((yy - 30) ** 2 + (xx - (c + radius)) ** 2 <= radius**2) & (labels == 0)] = 2
    labels[(yy - 75) ** 2 + (xx - 20) ** 2 <= 8**2] = 3
    return labels


def image_with_neck(labels: np.ndarray, neck: float) -> np.ndarray:
    """Dark particles on a bright film; the contact ridge of discs 1 and 2 at ``neck`` of the way from the background
    grey to the particles'."""
    from drgan.data.necks import contact_pairs

    image = np.where(labels > 0, PARTICLE, BACKGROUND)
    ridge = contact_pairs(labels)[0]
    image[ridge] = BACKGROUND + neck * (PARTICLE - BACKGROUND)
    return image


@pytest.mark.parametrize("neck", [1.0, 0.4, 0.0])
def test_a_contacts_neck_grey_is_its_ridge_on_the_particles_scale(neck):
    labels = two_touching_discs()
    found = necks(image_with_neck(labels, neck), labels)
    assert [(n.a, n.b) for n in found] == [(1, 2)]  # disc 3 touches nothing
    assert found[0].grey == pytest.approx(neck, abs=1e-9)
    # two discs of radius 14 touching at one point: a ridge a few px long against a 28-px diameter
    assert 0.0 < found[0].width < 0.5


def test_contact_statistics_count_hidden_necks_and_particles_touching():
    labels = two_touching_discs()
    hidden, visible = image_with_neck(labels, 1.0), image_with_neck(labels, 0.3)
    stats = contact_statistics([hidden, visible], [labels, labels])
    assert stats["contacts"] == 2 and stats["hidden"] == 0.5 and stats["gap"] == 0.5
    assert stats["contacts_per_particle"] == pytest.approx(4 / 6, abs=1e-3) and stats["touching"] == pytest.approx(
        4 / 6, abs=1e-3
    )
    assert contact_counts(labels) == (3, 2, 2)  # 3 particles, the pair counted once per particle, 2 touching
    assert contact_statistics([hidden], [np.where(labels == 2, 0, labels)]) is None  # no contact left
    assert HIDDEN_NECK < 1.0


def test_the_contact_check_warns_when_the_generated_contacts_hide_their_neck_more_often(caplog):
    from drgan.synthetic.contact_check import WARN_HIDDEN, log_result

    side = lambda hidden: {"hidden": hidden}  # noqa: E731
    with caplog.at_level(logging.INFO, logger="drgan.synthetic.contact_check"):
        log_result({"real": side(0.30), "generated": side(0.38), "generated_exact": side(0.60),
                    "hidden_difference": 0.30, "polarity": "dark"})  # fmt: skip
        log_result({"real": side(0.12), "generated": side(0.19), "generated_exact": side(0.57),
                    "hidden_difference": 0.45, "polarity": "bright"})  # fmt: skip
        log_result({"real": side(0.30), "generated": side(0.2), "generated_exact": side(0.32),
                    "hidden_difference": 0.02})  # fmt: skip
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 2 and "60%" in warned[0] and "30%" in warned[0] and 0.02 < WARN_HIDDEN < 0.30
    assert "placement.max_height" in warned[0] and "recapture" in warned[1]  # the cause by polarity


def test_a_handful_of_real_contacts_is_not_compared(caplog):
    from drgan.synthetic.contact_check import MIN_REAL_CONTACTS, hidden_difference, log_result

    exact = {"contacts": 37, "hidden": 0.405}
    assert hidden_difference({"contacts": MIN_REAL_CONTACTS, "hidden": 0.25}, exact) == pytest.approx(0.155)
    assert hidden_difference({"contacts": 1, "hidden": 0.0}, exact) is None  # one contact: no share to compare
    assert hidden_difference(None, exact) is None and hidden_difference({"contacts": 50, "hidden": 0.1}, None) is None
    with caplog.at_level(logging.INFO, logger="drgan.synthetic.contact_check"):
        log_result({"real": {"contacts": 1, "hidden": 0.0}, "generated": {"hidden": 0.13}, "generated_exact": exact,
                    "hidden_difference": None, "polarity": "dark"})  # fmt: skip
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "1 real contacts are too few to compare" in caplog.text
