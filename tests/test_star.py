"""The star-convex segmenter: ray-distance targets, the polygon split, and a run end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drgan.metrics.instance_scores import binarize_and_label, match_instances
from drgan.scene.labels import centre_distance, class_mask
from drgan.segmenters.inference import split_by_stars
from drgan.segmenters.polygons import ray_distances

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_ray_distances_reach_half_way_to_the_first_pixel_outside():
    labels = np.zeros((24, 24), np.int32)
    labels[10:15, 10:15] = 1  # a 5 x 5 square, its centre pixel (12, 12)
    labels[10:15, 15:18] = 2  # a neighbour to its right: another label ends a ray too
    rays = ray_distances(labels, 4, 16)  # angles 0 (+x), 90 (+y), 180 (-x), 270 (-y) degrees
    assert rays[:, 12, 12].tolist() == [2.5, 2.5, 2.5, 2.5]
    assert rays[:, 10, 10].tolist() == [4.5, 4.5, 0.5, 0.5]
    assert rays[0, 12, 17] == 0.5 and rays[2, 12, 17] == 2.5  # the neighbour's own rays
    assert not rays[:, 0, 0].any()  # off the particles
    long = np.zeros((4, 40), np.int32)
    long[1, :] = 1
    assert ray_distances(long, 4, 8)[0, 1, 0] == 7.5  # at most ray_px - 0.5


def exact_outputs(labels: np.ndarray, n_rays: int = 16, contact_line: bool = True) -> np.ndarray:
    """The outputs a perfect star-convex segmenter would give for ``labels``: classes, object probability, rays."""
    classes = class_mask(labels, 1)
    if not contact_line:
        classes[(classes == 2) & (labels > 0)] = 1  # the network drew no line where the two touch: one blob
        classes[np.isin(labels, [0])] = 0
    onehot = np.stack([(classes == c).astype(np.float32) for c in range(3)])
    return np.concatenate([onehot, centre_distance(labels)[None], ray_distances(labels, n_rays, 32)])


def two_touching_discs(size=64, r=9.0, gap=13.0):
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    c = size / 2
    labels[(yy - c) ** 2 + (xx - c + gap / 2) ** 2 <= r * r] = 1
    labels[((yy - c) ** 2 + (xx - c - gap / 2) ** 2 <= r * r) & (labels == 0)] = 2
    return labels


def test_touching_particles_come_apart_by_their_polygons_even_without_a_contact_line():
    labels = two_touching_discs()
    for line in (True, False):
        found = binarize_and_label(split_by_stars(exact_outputs(labels, contact_line=line), 0.5).astype(np.int64))
        match = match_instances(found, labels)
        assert match.tp == 2 and match.fp == 0 and match.fn == 0
        assert min(match.ious) > 0.85  # outlines from the classes: pixel-exact but for the 1-px separating line
    single = (labels > 0).astype(np.int32) * 0
    single[labels == 1] = 1
    found = binarize_and_label(split_by_stars(exact_outputs(single), 0.5).astype(np.int64))
    assert found.max() == 1  # one particle stays one, whatever its local maxima


def test_nothing_above_the_seed_level_finds_nothing():
    outputs = exact_outputs(two_touching_discs())
    outputs[3] *= 0.2
    assert not split_by_stars(outputs, 0.5).any()
    with pytest.raises(Exception, match="rays"):
        split_by_stars(outputs[:5], 0.5)


def test_the_star_segmenter_trains_calibrates_and_predicts(tmp_path):
    from conftest import compose
    from test_closed_loop import make_labelled_set
    from test_segment import tiny_segment_overrides

    from drgan.segment import segment
    from drgan.segmenters.inference import predict
    from drgan.segmenters.module import load_segmenter

    data = make_labelled_set(tmp_path / "gen", n=16)
    out = tmp_path / "run"
    extra = [
        "trainer.max_epochs=1",
        "model._target_=drgan.segmenters.star.StarSegmenterModule",
        "+model.n_rays=8",
        "+model.ray_px=16",
    ]
    segment(compose(tiny_segment_overrides(data, tmp_path, out, *extra), config_name="segment"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["split_calibration"]["split"] == "star" and "seed_level" in metrics["split_calibration"]
    model = load_segmenter(out / "checkpoints" / "last.ckpt")
    assert model.rays == 8 and model.split_calibration["split"] == "star"
    image = np.random.default_rng(0).random((40, 40)).astype(np.float32)
    classes = predict(model, image, tile=32, pixel_scale=0.5)  # rays rescaled with the image
    assert classes.shape == (40, 40) and set(np.unique(classes)) <= {0, 1, 2}
