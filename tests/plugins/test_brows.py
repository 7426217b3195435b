"""The brows' own expression distance and the region of the texture it weighs (persona.plugins.face.brows)."""

import numpy as np

from persona.plugins.face import brows
from persona.plugins.face.template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W, generic_template


def test_the_brows_distance_is_where_they_lie_from_their_eyes():
    """Raising both brows 2 px gives 10 points × 4 px²; moving a brow with its eye, or the mouth, gives 0; a
    point unknown in a photo is left out and the sum scaled back to all ten."""
    base = generic_template().fiducials3d[:, :2]
    raised, moved, mouth = base.copy(), base.copy(), base.copy()
    brow_points = [i for brow, _ in brows.BROWS for i in brow]
    raised[brow_points, 1] -= 2.0
    left_brow, left_eye = brows.BROWS[0]
    moved[list(left_brow) + list(left_eye)] += (3.0, -1.5)
    mouth[31:, 1] += 8.0  # the lips and the mouth's corners
    d2 = brows.square_distance(np.stack([raised, moved, mouth]), base)
    np.testing.assert_allclose(d2, [40.0, 0.0, 0.0], atol=1e-9)
    half = raised.copy()
    half[left_brow[0]] = np.nan
    np.testing.assert_allclose(brows.square_distance(half[None], base), [40.0])
    assert np.isnan(brows.square_distance(np.full((1, 49, 2), np.nan), base)).all()


def test_the_region_is_above_the_eyes_and_between_the_brows_down_to_the_inner_corners():
    """Over the brows it is 1, at the eyes' middles under 0.05 (its feather; the eyes' own region lies over it)
    and below them 0; between the eyes it reaches down to the
    line joining their inner corners (the creases between the brows); unknown lids give no region."""
    neutral = generic_template().fiducials3d[:, :2]
    region = brows.region(neutral, (H, W))
    for brow, eye in brows.BROWS:
        x, y = np.round(neutral[list(brow)].mean(axis=0)).astype(int)
        assert region[y, x] > 0.99
        x, y = np.round(neutral[list(eye)].mean(axis=0)).astype(int)
        assert region[y, x] < 0.05 and region[y + 6, x] < 0.001
    inner = neutral[[brows.BROWS[0][1][3], brows.BROWS[1][1][0]]]  # iBUG 39 and 42
    x, y = np.round(inner.mean(axis=0)).astype(int)
    assert region[y - 9, x] > 0.95 and region[y + 4, x] < 0.05
    assert not brows.region(np.full((49, 2), np.nan), (H, W)).any()
