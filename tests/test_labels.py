"""3-class masks from instance labels, checked against hand-drawn cases."""

import numpy as np
import pytest

from drgan.core.errors import ConfigError
from drgan.scene.labels import class_mask


def test_one_pixel_contour_of_a_square():
    labels = np.zeros((7, 7), int)
    labels[1:6, 1:6] = 1
    expected = np.zeros((7, 7), np.uint8)
    expected[1:6, 1:6] = 2
    expected[2:5, 2:5] = 1  # the 3x3 interior keeps the particle class
    np.testing.assert_array_equal(class_mask(labels, 1), expected)


def test_contour_never_overwrites_a_neighbour():
    labels = np.zeros((6, 10), int)
    labels[:, 1:5] = 1
    labels[:, 5:9] = 2  # touching particles
    mask = class_mask(labels, 1)
    # Each particle gets its own rim on its own side of the shared edge, and pixels stay theirs.
    assert (mask[:, 4] == 2).all() and (mask[:, 5] == 2).all()
    assert (mask[labels == 0] == 0).all()
    assert (mask[1:5, 2:4] == 1).all() and (mask[1:5, 6:8] == 1).all()


def test_contour_width_counts_pixels():
    labels = np.zeros((20, 20), int)
    labels[2:18, 2:18] = 1
    for width in (1, 2, 4):
        mask = class_mask(labels, width)
        row = mask[10]
        assert (row[2 : 2 + width] == 2).all() and row[2 + width] == 1, (width, row)


def test_image_border_is_not_a_boundary():
    labels = np.ones((5, 5), int)
    assert (class_mask(labels, 1) == 1).all()


def test_zero_width_gives_two_classes():
    labels = np.zeros((4, 4), int)
    labels[1:3, 1:3] = 3
    assert set(np.unique(class_mask(labels, 0))) == {0, 1}


@pytest.mark.parametrize("width", [-1, 1.5, True])
def test_bad_contour_width(width):
    with pytest.raises(ConfigError, match="contour_px"):
        class_mask(np.zeros((3, 3), int), width)
