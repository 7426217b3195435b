"""Eyelids that close (persona.plugins.face.eyes) on a synthetic texture with a known answer."""

from __future__ import annotations

import numpy as np

from persona.plugins.face import eyes
from persona.plugins.face.template import generic_template


def texture_with_dark_eyes():
    """Skin (180, 140, 120) with the two eye polygons of the template's fiducials painted dark."""
    import cv2

    neutral = generic_template().fiducials3d[:, :2].astype(np.float64)
    texture = np.zeros((244, 194, 3), np.float32) + (180, 140, 120)
    for points, _ in eyes.EYES:
        cv2.fillPoly(texture, [np.round(neutral[list(points)]).astype(np.int32)], (30, 20, 20))
    return texture, neutral


def shut(neutral, ratio):
    """The neutral fiducials with every lid pair brought to ``ratio`` of its distance."""
    target = neutral.copy()
    for _, pairs in eyes.EYES:
        for upper, lower in pairs:
            middle, half = (target[upper, 1] + target[lower, 1]) / 2, (target[lower, 1] - target[upper, 1]) / 2
            target[upper, 1], target[lower, 1] = middle - ratio * half, middle + ratio * half
    return target


def test_a_shut_eye_is_drawn_over_with_skin_and_an_open_one_is_left_alone():
    texture, neutral = texture_with_dark_eyes()
    np.testing.assert_allclose(eyes.closure(neutral, neutral), 0)
    np.testing.assert_allclose(eyes.closure(shut(neutral, 0.3), neutral), 1)
    half = eyes.closure(shut(neutral, 0.55), neutral)
    assert np.all((half > 0.2) & (half < 0.8))  # half way between 65 % and 45 %
    assert np.array_equal(eyes.close(texture, neutral, eyes.closure(neutral, neutral)), texture)
    closed = eyes.close(texture, neutral, eyes.closure(shut(neutral, 0.3), neutral))
    for points, _ in eyes.EYES:
        centre = np.round(neutral[list(points)].mean(axis=0)).astype(int)
        pixel = closed[centre[1], centre[0]]
        print(f"\neye centre: before {texture[centre[1], centre[0]]}, shut {pixel}")
        assert np.abs(pixel - (180, 140, 120)).max() < 12  # the skin around it, within 12 levels
    far = np.s_[200:, :]  # the chin: untouched
    assert np.array_equal(closed[far], texture[far])
