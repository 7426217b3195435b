"""Eyelids that close (persona.plugins.face.eyes) on a synthetic texture with a known answer."""

from __future__ import annotations

import cv2
import numpy as np

from persona.plugins.face import eyes
from persona.plugins.face.template import generic_template


def eye_mask(neutral, points):
    """(244, 194) bool: inside the polygon of an eye's six ``points`` of the fiducials ``neutral``."""
    mask = np.zeros((244, 194), np.uint8)
    cv2.fillPoly(mask, [np.round(neutral[list(points)]).astype(np.int32)], 1)
    return mask > 0


def texture_with_dark_eyes():
    """Skin (180, 140, 120) with the two eye polygons of the template's fiducials painted dark."""
    neutral = generic_template().fiducials3d[:, :2].astype(np.float64)
    texture = np.zeros((244, 194, 3), np.float32) + (180, 140, 120)
    for points, _ in eyes.EYES:
        texture[eye_mask(neutral, points)] = (30, 20, 20)
    return texture, neutral


def shut(neutral, ratio):
    """The neutral fiducials with every lid pair brought to ``ratio`` of its distance."""
    target = neutral.copy()
    for _, pairs in eyes.EYES:
        for upper, lower in pairs:
            middle, half = (target[upper, 1] + target[lower, 1]) / 2, (target[lower, 1] - target[upper, 1]) / 2
            target[upper, 1], target[lower, 1] = middle - ratio * half, middle + ratio * half
    return target


def test_a_shut_eye_is_drawn_over_with_skin_and_lashes_and_an_open_one_is_left_alone():
    texture, neutral = texture_with_dark_eyes()
    np.testing.assert_allclose(eyes.closure(neutral, neutral), 0)
    np.testing.assert_allclose(eyes.closure(shut(neutral, 0.3), neutral), 1)
    half = eyes.closure(shut(neutral, 0.55), neutral)
    assert np.all((half > 0.2) & (half < 0.8))  # half way between 65 % and 45 %
    assert np.array_equal(eyes.close(texture, neutral, eyes.closure(neutral, neutral)), texture)
    closed = eyes.close(texture, neutral, eyes.closure(shut(neutral, 0.3), neutral))
    for points, _ in eyes.EYES:
        pixels = closed[eye_mask(neutral, points)]
        skin = np.abs(pixels - (180, 140, 120)).max(axis=1) < 12
        print(f"\nshut eye: {skin.mean():.0%} of it skin (within 12 levels), mean {pixels.mean(axis=0)}, "
              f"darkest {pixels.min(axis=0)}")
        assert skin.mean() > 0.35 and pixels.mean() > 0.7 * np.mean((180, 140, 120))  # was all dark: skin, but for
        assert pixels.sum(axis=1).min() < 3 * 90  # the line of lashes, the eye's dark colour
    far = np.s_[200:, :]  # the chin: untouched
    assert np.array_equal(closed[far], texture[far])
