"""Gaze against known iris positions: the iris is found in a drawn eye where it was drawn, and a
texture's eye turned by a shift is found looking where the shift says, with its white behind the iris
and its lids, corners and skin left in place."""

import cv2
import numpy as np
import pytest

from persona.plugins.face import gaze


def drawn_eye(width: float, u: float, v: float, seed: int = 0, iris: float = 0.42, colour=(90, 60, 40),
              pupil: bool = True):
    """(image, the eye's six iBUG points): an almond eye ``width`` px from corner to corner on skin, with a lash
    line along its upper lid and an iris ``iris`` of its width across, of ``colour``, with a black ``pupil``, whose
    centre is (u, v) eye widths from the middle of its corners (u right, v down), drawn 4 times finer and
    averaged down, with noise (σ 3)."""
    fine, side = 4, int(width * 3)
    image = np.full((side * fine, side * fine, 3), (200, 160, 140), np.uint8)
    cx = cy = side / 2
    height = 0.32 * width
    t = np.linspace(0, np.pi, 40)
    upper = np.c_[cx - np.cos(t) * width / 2, cy - np.sin(t) * height / 2 * 1.15]
    lower = np.c_[cx + np.cos(t) * width / 2, cy + np.sin(t) * height / 2 * 1.15]
    opening = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(opening, [np.round(np.vstack([upper, lower]) * fine).astype(np.int32)], 1)
    eye = np.full_like(image, 235)
    centre = (int((cx + u * width) * fine), int((cy + v * width) * fine))
    cv2.circle(eye, centre, int(iris / 2 * width * fine), colour, -1)
    if pupil:
        cv2.circle(eye, centre, int(0.08 * width * fine), (15, 10, 10), -1)
    image = np.where(opening[..., None] > 0, eye, image)
    cv2.polylines(image, [np.round(upper * fine).astype(np.int32)], False, (30, 25, 25), max(1, int(0.04 * width * fine)))
    image = cv2.resize(image, (side, side), interpolation=cv2.INTER_AREA)
    image = np.clip(image + np.random.default_rng(seed).normal(0, 3, image.shape), 0, 255).astype(np.uint8)
    points = np.array([[cx - width / 2, cy], [cx - width / 6, cy - height / 2], [cx + width / 6, cy - height / 2],
                       [cx + width / 2, cy], [cx + width / 6, cy + height / 2], [cx - width / 6, cy + height / 2]])
    return image, points


@pytest.mark.parametrize("width, tolerance", [(60, 0.03), (25, 0.035), (14, 0.05)])
def test_the_iris_is_found_where_it_was_drawn(width, tolerance):
    """Within ``tolerance`` eye widths, along and across, from an HD eye (60 px) to a tight crop's (14 px,
    about 5 px between the lids); 15 places from -0.2 to 0.2 along and -0.04 to 0.04 across."""
    for u in (-0.2, -0.1, 0.0, 0.1, 0.2):
        for v in (-0.04, 0.0, 0.04):
            image, points = drawn_eye(width, u, v)
            found = gaze.iris_offset(image, points)
            assert np.abs(found - (u, v)).max() < tolerance, (width, u, v, found)


@pytest.mark.parametrize("width", [60, 25, 14])
def test_an_iris_half_under_a_lid_is_found_where_it_is(width):
    """Irises drawn from 0.15 eye widths up to 0.15 down (the lids hide up to a third of them) and from 0.3 left
    to 0.3 right: what the measure finds rises with where they were drawn at a slope of 0.85-1.15 across the eye
    and 0.95-1.05 along it (measured 0.88-0.94 and 0.97-1.01; a disc whose centre must lie in the opening finds
    0.39-0.58 and 0.88-0.92)."""
    across = np.linspace(-0.15, 0.15, 7)
    along = np.linspace(-0.3, 0.3, 7)
    found_across = [gaze.iris_offset(*drawn_eye(width, 0.1, v))[1] for v in across]
    found_along = [gaze.iris_offset(*drawn_eye(width, u, 0.0))[0] for u in along]
    assert 0.85 < np.polyfit(across, found_across, 1)[0] < 1.15
    assert 0.95 < np.polyfit(along, found_along, 1)[0] < 1.05


def test_a_closed_eye_or_no_face_has_no_gaze():
    image, points = drawn_eye(40, 0.1, 0.0)
    shut = points.copy()
    shut[[1, 2], 1] = shut[[5, 4], 1] - 0.05 * 40  # lids 5 % of the width apart
    assert np.isnan(gaze.iris_offset(image, shut)).all()
    assert np.isnan(gaze.iris_offsets(image, np.full((68, 2), np.nan))).all()


@pytest.mark.parametrize("width", [40, 25, 14])
def test_a_texture_eye_turns_by_the_shift_under_its_lids(width):
    """B's texture's eye with its iris in the middle, turned 0.1, 0.2 and 0.3 of its width right, 0.2 left and
    0.05 down, 0.1 down: the iris is then found there, within 0.03 eye widths along the eye and 0.06 across it,
    0.035 and 0.07 on the 14-px eye (half a pixel along; the lids, close above and below, hide part of an iris
    that moves up or down, as they do a real one); where
    it was, the eye is white again (no iris left behind: the grey of the old centre over 200 when it went 0.3);
    the texels more than two beyond the opening do not change; no shift returns the texture itself."""
    image, points = drawn_eye(width, 0.0, 0.0)
    neutral = np.full((49, 2), np.nan)  # one eye drawn: the other's points unknown, left alone
    neutral[list(gaze.EYES49[0])] = points
    for shift in ((0.1, 0.0), (0.2, 0.0), (0.3, 0.0), (-0.2, 0.05), (0.0, 0.1)):
        moved = gaze.look(image.astype(np.float32), neutral, np.array([shift, shift]))
        found = gaze.iris_offset(np.clip(moved, 0, 255).round().astype(np.uint8), points)
        assert np.all(np.abs(found - shift) < ((0.035, 0.07) if width < 20 else (0.03, 0.06))), (shift, found)
    x, y = np.round((points[0] + points[3]) / 2).astype(int)
    assert moved.shape == image.shape and image[y, x].mean() < 60  # the drawn iris' middle, before
    far = gaze.look(image.astype(np.float32), neutral, np.array([[0.3, 0.0], [0.3, 0.0]]))
    assert far[y, x].mean() > 200
    opening = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(opening, [np.round(points).astype(np.int32)], 1)
    outside = cv2.dilate(opening, np.ones((9, 9), np.uint8)) == 0
    assert np.array_equal(far[outside], image[outside])  # the lids, the corners and the skin stay
    assert gaze.look(image, neutral, np.zeros((2, 2))) is image  # nothing to move


@pytest.mark.parametrize("width", [40, 25, 14])
@pytest.mark.parametrize("iris", [0.5, 0.56])
def test_a_wide_iris_turned_a_little_stays_whole(width, iris):
    """An iris wider than the measure's (half the eye's width or more, as a blend of photos makes it), turned
    0.02 eye widths: it keeps at least 96 % of its dark texels inside the opening (measured 97-100 %). A disc of
    the measure's size cut its rim off and filled it with white: 86-92 % was left, and on a real texture every
    frame's glance, however small, shrank the iris."""
    image, points = drawn_eye(width, 0.0, 0.0, iris=iris)
    neutral = np.full((49, 2), np.nan)
    neutral[list(gaze.EYES49[0])] = points
    texture = image.astype(np.float32)
    turned = gaze.look(texture, neutral, np.array([[0.02, 0.0], [0.0, 0.0]]))
    opening = gaze._coverage(image.shape[:2], gaze._almond(points)) > 0.5

    def dark(t):
        return int((t.mean(axis=-1)[opening] < (235 + 63) / 2).sum())  # nearer the iris' grey than the white's

    assert dark(turned) >= 0.96 * dark(texture), (dark(texture), dark(turned))


@pytest.mark.parametrize("width", [40, 25])
def test_the_turned_disc_reaches_a_dark_iris_edge_and_keeps_its_size_on_a_light_one(width):
    """The disc a turned iris moves in: a texel beyond a dark iris 0.56 of the eye wide (its drawn radius 0.28
    eye widths, within 1.5 texels), and the measure's own (IRIS / 2) on a light one (grey-blue, its middle less
    than IRIS_DARK of the white darker, its pupil washed out as in a blend of photos), whose edge does not
    show."""
    for colour, pupil, expected in (((90, 60, 40), True, 0.28 * width), ((150, 165, 180), False, gaze.IRIS * width / 2)):
        image, points = drawn_eye(width, 0.0, 0.0, iris=0.56, colour=colour, pupil=pupil)
        opening = gaze._coverage(image.shape[:2], gaze._almond(points))
        centre = (points[0] + points[3]) / 2
        found = gaze._iris_radius(image.astype(np.float32), opening, centre, width)
        assert abs(found - expected) <= 1.5, (colour, found, expected)


def test_the_white_behind_a_turned_iris_is_white_beside_a_dark_inner_corner():
    """An eye whose white shows little either side of its iris, its inner (left) corner a dark pink and its
    white shaded grey under the upper lid: turned 0.3 of its width right, the place the iris left (a tenth of
    the eye's width left of its middle, clear of the turned iris' rim) is filled from the white, not from the
    corner (its grey within 12 of the white's brightest tenth; filled from all the opening either side it was
    50 darker), and the measure finds the iris where it went (within 0.05)."""
    width = 25
    image, points = drawn_eye(width, 0.0, 0.0, seed=1)
    opening = np.zeros(image.shape[:2], np.uint8)
    cv2.fillPoly(opening, [np.round(points).astype(np.int32)], 1)
    corner = np.zeros_like(opening)
    cv2.circle(corner, tuple(np.round(points[0] + (0.12 * width, 0)).astype(int)), round(0.16 * width), 1, -1)
    image[(corner > 0) & (opening > 0)] = (150, 95, 95)
    neutral = np.full((49, 2), np.nan)
    neutral[list(gaze.EYES49[0])] = points
    far = gaze.look(image.astype(np.float32), neutral, np.array([[0.3, 0.0], [0.3, 0.0]]))
    x, y = np.round((points[0] + points[3]) / 2 - (0.1 * width, 0)).astype(int)
    white = np.percentile(image[(opening > 0) & (corner == 0)].mean(axis=1), 90)
    assert far[y, x].mean() > white - 12, (far[y, x], white)
    found = gaze.iris_offset(np.clip(far, 0, 255).round().astype(np.uint8), points)
    assert abs(found[0] - 0.3) < 0.05, found


def test_a_clips_gaze_is_taken_from_its_usual_one_each_eye_from_its_own_and_clipped():
    """Offsets (T, 2 eyes, 2) of a clip that looks ahead, at 0.05 eye widths right, in most frames: each eye's
    shift is its offset less its own median over the clip (frame 3: the left eye 0.07: 0.02, the right 0.05:
    0), clipped to MAX_SHIFT (0.5: 0.45 is more); an eye not measured takes the other's shift (frame 4's right
    eye); a frame without either eye measured moves nothing; ``together`` gives both eyes their mean."""
    offsets = np.zeros((6, 2, 2))
    offsets[:, 0, 0] = [0.05, 0.05, 0.05, 0.07, 0.5, np.nan]
    offsets[:, 1, 0] = [0.05, 0.05, 0.05, 0.05, np.nan, np.nan]
    offsets[4, 1] = np.nan
    offsets[5] = np.nan
    shift = gaze.gaze_shift(offsets)
    assert shift.shape == (6, 2, 2)
    assert np.abs(shift[:3]).max() < 1e-12
    assert shift[3, 0, 0] == pytest.approx(0.02) and shift[3, 1, 0] == pytest.approx(0.0)
    assert shift[4, 0, 0] == pytest.approx(gaze.MAX_SHIFT[0]) and np.array_equal(shift[4, 1], shift[4, 0])
    assert not shift[5].any()
    both = gaze.together(shift)
    assert both[3, 0, 0] == pytest.approx(0.01) and np.array_equal(both[:, 0], both[:, 1])


def test_eyes_turn_apart_where_the_clip_shows_it_above_the_measures_noise():
    """Two clips of 200 frames whose eyes look about together (a shared glance of 0.1 eye widths), each eye's
    measure with its own noise of 0.01 eye widths a frame (as on the HD clips). In the first the eyes also
    converge once, slowly, and part again (0.15 eye widths apart at most): each eye keeps its own turn. In the
    second they never turn apart, and both turn by their mean, where each eye alone would add its own noise.
    Either way both eyes' mean is the measure's."""
    rng = np.random.default_rng(5)
    t = np.arange(200)
    glance = 0.1 * np.sin(t / 9)
    for converge, kept in ((0.075 * np.exp(-((t - 100) / 25) ** 2), 1.0), (np.zeros(200), 0.0)):
        offsets = np.zeros((200, 2, 2))
        offsets[:, 0, 0] = glance + converge + rng.normal(0, 0.01, 200)
        offsets[:, 1, 0] = glance - converge + rng.normal(0, 0.01, 200)
        shift = gaze.gaze_shift(offsets)
        apart, measured = shift[:, 1, 0] - shift[:, 0, 0], offsets[:, 1, 0] - offsets[:, 0, 0]
        assert np.polyfit(measured - measured.mean(), apart, 1)[0] == pytest.approx(kept, abs=1e-9)
        wanted = offsets[:, :, 0].mean(axis=1) - np.median(offsets[:, :, 0], axis=0).mean()
        assert np.abs(shift[:, :, 0].mean(axis=1) - wanted).max() < 1e-9


def test_a_measure_of_noise_alone_spreads_as_far_as_its_noise_and_a_slow_turn_further():
    """spread_over_noise, the figure the texture's gaze and the evaluation's target for the eyes apart both read:
    2,000 frames of white noise (σ 0.02) stand at 1 (within 0.1); the same noise on a slow turn of 0.2 eye widths
    (a period of 300 frames) over twice APART_SNR; a frame with a NaN is left out; fewer than three frames, 0."""
    rng = np.random.default_rng(11)
    noise = rng.normal(0, 0.02, 2000)
    turn = 0.2 * np.sin(np.arange(2000) * 2 * np.pi / 300)
    ratio = gaze.spread_over_noise(np.c_[noise, turn + noise])
    assert ratio[0] == pytest.approx(1.0, abs=0.1) and ratio[1] > 2 * gaze.APART_SNR
    holed = np.c_[noise, turn + noise]
    holed[::7, 0] = np.nan
    assert gaze.spread_over_noise(holed)[1] == pytest.approx(ratio[1], rel=0.1)
    np.testing.assert_array_equal(gaze.spread_over_noise(np.zeros((2, 2))), [0, 0])


def test_eyes_never_part_further_than_eyes_do():
    """A clip whose eyes converge (the image's right one 0.15 eye widths towards the nose) in some frames and
    whose measure, in three frames, has them part by 0.3 (a glare on one lens): the convergence is kept, the
    parting is brought to MAX_PART, and each frame's mean of the two eyes stays the measure's."""
    offsets = np.zeros((60, 2, 2))
    offsets[20:30, 1, 0] = -0.15
    offsets[40:43, 1, 0] = 0.3
    shift = gaze.gaze_shift(offsets)
    apart = shift[:, 1, 0] - shift[:, 0, 0]
    assert apart[20:30] == pytest.approx(-0.15)
    assert apart[40:43] == pytest.approx(gaze.MAX_PART)
    assert shift[:, :, 0].mean(axis=1) == pytest.approx(offsets[:, :, 0].mean(axis=1))
