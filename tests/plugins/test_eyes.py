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
    assert np.array_equal(eyes.lower(texture, neutral, eyes.lowered(shut(neutral, 0.9), neutral)), texture)
    closed = eyes.lower(texture, neutral, eyes.lowered(shut(neutral, 0.3), neutral), meet=1)
    for points, _ in eyes.EYES:
        pixels = closed[eye_mask(neutral, points)]
        skin = np.abs(pixels - (180, 140, 120)).max(axis=1) < 12
        print(f"\nshut eye: {skin.mean():.0%} of it skin (within 12 levels), mean {pixels.mean(axis=0)}, "
              f"darkest {pixels.min(axis=0)}")
        assert skin.mean() > 0.35 and pixels.mean() > 0.7 * np.mean((180, 140, 120))  # was all dark: skin, but for
        assert pixels.sum(axis=1).min() < 3 * 90  # the line of lashes, the eye's dark colour
    far = np.s_[200:, :]  # the chin: untouched
    assert np.array_equal(closed[far], texture[far])


def test_the_upper_lid_comes_down_over_the_share_of_the_eye_a_real_one_would_cover():
    texture, neutral = texture_with_dark_eyes()
    lowered = lambda r: eyes.lowered(shut(neutral, r), neutral, start=0.85, end=0.45)
    np.testing.assert_allclose(eyes.lowered(neutral, neutral), 1)  # open: nothing covered
    np.testing.assert_allclose(lowered(0.86), 1)  # above 85 %: the mesh alone
    np.testing.assert_allclose(lowered(0.4), 0)  # below 45 %: shut
    # at 0.7 of the neutral distance a real eye shows 0.85 (0.7 - 0.45) / (0.85 - 0.45) = 0.531 of its
    # opening; the mesh squeezes it to 0.7, so the lid covers all but 0.531 / 0.7 = 0.759 of the squeezed eye
    np.testing.assert_allclose(lowered(0.7), 0.531 / 0.7, atol=0.005)
    assert np.array_equal(eyes.lower(texture, neutral, np.ones(2)), texture)
    for visible in (0.25, 0.5, 0.75):
        lowered = eyes.lower(texture, neutral, np.full(2, visible), meet=1)  # the upper lid alone comes down
        for points, _ in eyes.EYES:
            inside = eye_mask(neutral, points)
            rows = np.flatnonzero(inside.any(axis=1))
            dark = (lowered.sum(axis=2) < 3 * 60) & inside  # the eye still seen, and the line of lashes
            x1, x2 = neutral[list(points)][1:3, 0]  # the upper lid's two points: between them, away from the
            seen = np.flatnonzero(dark[:, int(np.ceil(x1)):int(x2) + 1].any(axis=1))  # corners, the edge is level
            # the dark part starts lower down (the lid's edge) and ends at the lower lid, as before
            top = (seen.min() - rows.min()) / (rows.max() - rows.min())
            print(f"\nvisible {visible}: dark from {top:.2f} of the eye's height down")
            assert abs(top - (1 - visible)) < 0.2 and seen.max() >= rows.max() - 1
            edge = rows.min() + (1 - visible) * (rows.max() - rows.min())
            above = inside & (np.arange(244)[:, None] < edge - 1)  # the lid, over what was the dark eye
            assert above.any() and (lowered[above].sum(axis=1) > 3 * 100).mean() > 0.9


def test_the_lid_comes_down_smoothly_not_in_whole_texel_steps():
    # the lid's edge moves 1/40 of the eye's height (about a sixth of a texel) a step: drawn in whole
    # texels, most steps changed nothing and a few a whole row at once
    texture, neutral = texture_with_dark_eyes()
    inside = eye_mask(neutral, eyes.EYES[0][0])
    shares = np.arange(0.8, 0.3, -0.025)  # of the eye left uncovered
    brightness = [eyes.lower(texture, neutral, np.full(2, v), meet=1)[inside].mean() for v in shares]
    steps = np.diff(brightness)
    print(f"\nthe eye's brightness a step: {np.round(steps, 2)}")
    assert steps.min() > 0 and steps.max() < 3 * np.median(steps)


def test_a_shut_eyes_lashes_lie_where_the_lids_meet_and_skin_covers_the_rest():
    """``meet``: the upper lid comes that share of the way down the opening and the lower lid rises the rest, so a
    shut eye is one line of lashes across skin, not the outline of an open eye (whose lower lid the line followed
    at ``meet`` 1)."""
    texture, neutral = texture_with_dark_eyes()
    for meet in (1.0, 0.6):
        closed = eyes.lower(texture, neutral, np.zeros(2), meet=meet)
        for points, _ in eyes.EYES:
            inside = eye_mask(neutral, points)
            rows = np.flatnonzero(inside.any(axis=1))
            x1, x2 = neutral[list(points)][1:3, 0]
            middle = np.s_[:, int(np.ceil(x1)):int(x2) + 1]  # between the upper lid's points: the line is level
            darkness = np.where(inside, 3 * 255 - closed.sum(axis=2), 0)[middle].sum(axis=1)
            line = (np.argmax(darkness) - rows.min()) / (rows.max() - rows.min())
            away = inside & (np.abs(np.arange(244) - np.argmax(darkness))[:, None] > 2)
            skin = (closed[away].sum(axis=1) > 3 * 100).mean()
            print(f"\nmeet {meet}: the lashes {line:.2f} of the eye's height down; {skin:.0%} skin away from them")
            assert abs(line - meet) < 0.15 and skin > 0.9


def test_by_default_a_half_shut_eye_is_drawn_half_open_and_a_blink_shut():
    """The texture's defaults: dlib reads the half-shut eyes of HD drivers at 0.6-0.7 of their usual opening and
    their blinks at 0.25-0.4. A half-shut eye keeps most of what the mesh squeezes it to (at ``shut_at`` 0.45 the lid
    covered 0.38 of it, and the eye was drawn as a slit of lashes), a blink's eye is all but covered, and a shut
    one wholly."""
    from persona.plugins.builtin.texture import MultiscaleTexture
    p = MultiscaleTexture.Params()
    _, neutral = texture_with_dark_eyes()
    assert (p.shut_from, p.shut_at) == (eyes.SHUT_FROM, eyes.SHUT_AT)
    visible = {r: eyes.lowered(shut(neutral, r), neutral) for r in (0.65, 0.38, 0.3)}
    print({r: np.round(v, 3) for r, v in visible.items()})
    assert (visible[0.65] > 0.8).all()  # 0.9 (0.65 - 0.3) / (0.9 - 0.3) / 0.65 = 0.808
    assert (visible[0.38] < 0.35).all() and (visible[0.3] == 0).all()


def test_a_lid_fades_in_so_an_eye_just_narrower_than_neutral_keeps_its_look():
    """Past ``shut_from`` the lid starts down; drawn at full strength at once, it and its line of lashes lay over
    the texture's own lid and lashes and made a dark line of eyeliner across an eye the lid had barely moved over."""
    texture, neutral = texture_with_dark_eyes()
    inside = np.logical_or(*(eye_mask(neutral, points) for points, _ in eyes.EYES))

    def changed(ratio, **kw):
        lowered = eyes.lower(texture, neutral, eyes.lowered(shut(neutral, ratio), neutral), **kw)
        return float(np.abs(texture - lowered)[inside].sum(axis=1).max())  # the most any texel of the eyes moved

    just_past, further = changed(0.88), changed(0.45)
    print(f"\nchanged at 0.88 of the neutral opening: {just_past:.0f} (drawn at once: {changed(0.88, fade=0):.0f}); "
          f"at 0.45: {further:.0f} (at once: {changed(0.45, fade=0):.0f})")
    assert changed(0.88, fade=0) > 100  # as it was: a lid and lashes drawn in full on a lid moved 0.1 texel
    assert just_past < 0.15 * changed(0.88, fade=0)  # now a trace
    assert further == changed(0.45, fade=0)  # a lid that came down further than the fade is drawn as before
