"""Smoothing TPS (Eq. 1), retargeting, bridging and the baseline renderer's geometry."""

import cv2
import numpy as np
import pytest

from persona.plugins.builtin.frontalize import project, template_points
from persona.plugins.builtin.render import Tps2dRender, canonical_coordinates
from persona.plugins.face.template import IDX49, generic_template
from persona.plugins.face.tracks import bridge
from persona.plugins.face.warp import (FACING, LOWER_LIP, UPPER_LIP, TpsWarp, close_no_further, eye_mouth_scale,
                                       eye_opening, lip_gap, pin, retarget, tps_map, tps_smoothing)
from persona.plugins.kinds import Pose, Puppet


def smooth_warp(points):
    x, y = points[:, 0], points[:, 1]
    return np.c_[1.02 * x + 0.05 * y + 3 + 2 * np.sin(y / 30), -0.03 * x + 0.98 * y - 2 + 1.5 * np.cos(x / 25)]


def test_tps_interpolates_without_smoothing_and_tends_to_affine_with_a_lot():
    target = generic_template().landmarks3d[list(IDX49), :2]
    source = smooth_warp(target)
    exact = tps_map(target, source, (244, 194), lam=0.0)
    sampled = np.stack([cv2.remap(exact[..., c], target[:, 0].astype(np.float32)[None],
                                  target[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)[0] for c in (0, 1)], 1)
    integer = np.abs(target - target.round()).max(axis=1) < 1e-9
    np.testing.assert_allclose(sampled[integer], source[integer], atol=1e-3)
    stiff = tps_map(target, source, (244, 194), lam=1e9)
    design = np.c_[np.ones(len(target)), target]
    coef = np.linalg.lstsq(design, source, rcond=None)[0]
    ys, xs = np.mgrid[0:244, 0:194]
    affine = (np.c_[np.ones(xs.size), xs.ravel(), ys.ravel()] @ coef).reshape(244, 194, 2)
    assert np.abs(stiff - affine).max() < 1e-2


def test_tps_matches_the_hand_built_system():
    """(K + sI) a + P b = d with K = r² log r and s = 8πλ (ALGORITHMS §5)."""
    rng = np.random.default_rng(0)
    target = rng.uniform(20, 170, (12, 2))
    source = smooth_warp(target)
    lam = 10.0
    s = tps_smoothing(lam, len(target))
    assert s == pytest.approx(8 * np.pi * 10)
    r = np.linalg.norm(target[:, None] - target[None], axis=2)
    k = np.where(r > 0, r ** 2 * np.log(np.where(r > 0, r, 1)), 0)
    p = np.c_[np.ones(len(target)), target]
    system = np.block([[k + s * np.eye(len(target)), p], [p.T, np.zeros((3, 3))]])
    coef = np.linalg.solve(system, np.r_[source, np.zeros((3, 2))])
    query = np.array([[50.0, 60.0], [120.0, 200.0]])
    rq = np.linalg.norm(query[:, None] - target[None], axis=2)
    expected = (rq ** 2 * np.log(rq)) @ coef[:-3] + np.c_[np.ones(2), query] @ coef[-3:]
    got = tps_map(target, source, (244, 194), lam=lam)[[60, 200], [50, 120]]
    np.testing.assert_allclose(got, expected, atol=1e-3)
    assert tps_smoothing(lam, 12, "diagonal") == 10 and tps_smoothing(lam, 12, "wahba") == pytest.approx(8 * np.pi * 120)


def test_retarget_scales_offsets_to_the_puppets_proportions():
    driver_neutral = generic_template().landmarks3d[list(IDX49), :2]
    puppet_neutral = (driver_neutral - 97) * [1.2, 0.9] + 97
    assert np.allclose(eye_mouth_scale(puppet_neutral) / eye_mouth_scale(driver_neutral), [1.2, 0.9])
    offsets = np.zeros((3, 49, 2))
    offsets[1, 40, 1] = 5.0  # the lip moves down 5 px
    target = retarget(driver_neutral + offsets, driver_neutral, puppet_neutral)
    np.testing.assert_allclose(target[0], puppet_neutral)
    assert target[1, 40, 1] - puppet_neutral[40, 1] == pytest.approx(4.5)


def test_bridge_interpolates_gaps_and_holds_the_ends():
    values = np.array([np.nan, 1.0, np.nan, np.nan, 4.0, np.nan])
    found = np.isfinite(values)
    np.testing.assert_allclose(bridge(values, found), [1, 1, 2, 3, 4, 4])
    with pytest.raises(ValueError, match="no frame"):
        bridge(values, np.zeros(6, bool))


def pose(yaw=15.0):
    template = generic_template()
    rvec = np.radians([5.0, yaw, 0.0])
    rotation = cv2.Rodrigues(rvec)[0]
    tvec = np.array([0, 0, 700.0]) - rotation @ template.landmarks3d.mean(axis=0)
    camera = np.array([[400.0, 0, 127.5], [0, 400.0, 127.5], [0, 0, 1]])
    return Pose(rvec, tvec, camera, 0.0)


def test_canonical_coordinates_round_trip():
    """Each frame pixel's canonical point projects back onto that pixel."""
    p = pose()
    where, hit = canonical_coordinates(p, (256, 256))
    assert 0.1 < hit.mean() < 0.9
    template = generic_template()
    rows, cols = np.nonzero(hit)
    back = project(template_points(template.depth, where[rows, cols].astype(np.float64)), p)[0]
    error = np.hypot(back[:, 0] - cols, back[:, 1] - rows)
    assert np.median(error) < 0.05 and np.percentile(error, 95) < 0.5  # bilinear depth at steep parts


def test_render_shows_the_puppet_where_the_face_is_and_grey_elsewhere():
    template = generic_template()
    appearance = np.zeros((244, 194, 3), np.float32)
    appearance[..., 0] = 200  # a red face
    puppet = Puppet(appearance, template.mask.astype(np.float32), template.landmarks3d[list(IDX49), :2])
    frame = np.full((256, 256, 3), (0, 90, 0), np.uint8)
    out = Tps2dRender().render(puppet, puppet.fiducials, pose(), frame)
    assert out.rgb.shape == frame.shape and out.rgb.dtype == np.uint8
    inside, outside = out.mask > 0.99, out.mask == 0
    assert inside.sum() > 5000 and outside.sum() > 5000
    assert np.abs(out.rgb[out.mask > 0].astype(int) - [200, 0, 0]).max() <= 1  # the soft edge too (Rendered)
    assert (out.rgb[outside] == 128).all()  # the driver's frame is the composite's, not the render's


def test_coarse_tps_evaluation_is_close_to_exact():
    target = generic_template().landmarks3d[list(IDX49), :2]
    source = smooth_warp(target)
    exact = tps_map(target, source, (244, 194), lam=10)
    coarse = tps_map(target, source, (244, 194), lam=10, step=4)
    assert coarse.shape == exact.shape
    assert np.abs(coarse - exact).max() < 0.05


def test_prepared_tps_warp_equals_tps_map_for_any_source():
    rng = np.random.default_rng(5)
    target = rng.uniform(10, 180, (30, 2))
    for step in (1, 4):
        warp = TpsWarp(target, (60, 50), lam=3.0, step=step)
        for _ in range(2):
            source = target + rng.normal(0, 3, target.shape)
            np.testing.assert_allclose(warp.map(source), tps_map(target, source, (60, 50), lam=3.0, step=step),
                                       atol=2e-3)


def test_pin_sends_the_points_home():
    """A map that misses its landmarks by up to 3 px (a smooth drift, as a flow between two blurred
    averages can) is pinned: λ = 0 sends every point within 0.2 px of its mate (the spline is
    evaluated on every 4th pixel), λ = 1 within 0.7 px (smoothing); a point given as NaN is left out."""
    rng = np.random.default_rng(3)
    h, w = 120, 100
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    drift = np.stack([1.5 * np.sin(ys / 15), 3 * np.exp(-((xs - 50) ** 2 + (ys - 80) ** 2) / 60)], axis=-1)
    map_ = np.stack([xs, ys], axis=-1) + drift.astype(np.float32)
    target = rng.uniform([30, 30], [70, 90], (20, 2))
    source = target.copy()  # the truth: the identity
    source[5] = np.nan
    for lam, tol in ((0.0, 0.2), (1.0, 0.7)):
        pinned = pin(map_, target, source, lam=lam)
        at = cv2.remap(pinned, target[:, 0].astype(np.float32)[None], target[:, 1].astype(np.float32)[None],
                       cv2.INTER_LINEAR)[0]
        miss = np.linalg.norm(at - source, axis=1)
        assert np.nanmax(miss) < tol, (lam, miss)
        before = np.linalg.norm(cv2.remap(map_, target[:, 0].astype(np.float32)[None],
                                          target[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)[0] - target, axis=1)
        assert np.nanmax(before) > 1.0  # the test would see a no-op
    assert np.all(np.isfinite(pinned))


def test_retarget_from_the_puppets_own_neutral_gives_the_drivers_fiducials_back():
    """A self-reenactment measured from the driver's collection (``neutral: collection``, what 'auto' picks
    when the driver is the puppet): the driver's neutral is the puppet's, so every rule of the retarget
    (lids, lips, proportions) leaves a frame where it is, a surprise held through the clip included (brows
    up 4 px, eyes 3 px wider, mouth 6 px open), to 0.1 px; from the clip's mean it would be taken out."""
    neutral = generic_template().landmarks3d[list(IDX49), :2]
    surprise = neutral.copy()
    surprise[:10, 1] -= 4.0  # the brows
    for upper, lower in FACING[:4]:
        surprise[upper, 1] -= 1.5
        surprise[lower, 1] += 1.5
    surprise[list(LOWER_LIP), 1] += 6.0
    frames = np.stack([neutral, surprise, surprise, (neutral + surprise) / 2])
    for lips in ("mean", "parted", "closed"):
        for widen in ("opening", "face"):
            np.testing.assert_allclose(retarget(frames, neutral, neutral, lips=lips, widen=widen), frames, atol=0.1)
    from_clip = retarget(frames, frames.mean(axis=0), neutral)
    assert np.abs(from_clip[1, :10, 1] - surprise[:10, 1]).min() > 1.0  # the held brows are taken out


def test_retarget_closes_the_puppets_own_eyes_and_never_crosses_the_lids():
    """A blink that closes the driver's eyes closes the puppet's, which are 30 % smaller: the lids'
    offsets are scaled by the eye openings (not by the face's height); a larger offset stops at
    closed instead of passing the lower lid."""
    driver_neutral = generic_template().landmarks3d[list(IDX49), :2]
    puppet_neutral = driver_neutral.copy()
    for upper, lower in FACING[:4]:  # the puppet's eyes open 30 % less, about their middle line
        middle, half = (driver_neutral[upper, 1] + driver_neutral[lower, 1]) / 2, (driver_neutral[lower, 1] - driver_neutral[upper, 1]) / 2
        puppet_neutral[upper, 1], puppet_neutral[lower, 1] = middle - 0.7 * half, middle + 0.7 * half
    assert eye_opening(puppet_neutral) / eye_opening(driver_neutral) == pytest.approx(0.7)
    blink = driver_neutral.copy()
    for upper, lower in FACING[:4]:
        blink[upper, 1] = blink[lower, 1]  # the upper lid comes down onto the lower one
    beyond = blink.copy()
    for upper, _ in FACING[:4]:
        beyond[upper, 1] += 3.0  # 3 px past it
    target = retarget(np.stack([driver_neutral, blink, beyond]), driver_neutral, puppet_neutral)
    np.testing.assert_allclose(target[0], puppet_neutral)
    for upper, lower in FACING[:4]:
        assert target[1, lower, 1] - target[1, upper, 1] == pytest.approx(0.0, abs=1e-9)  # closed
        assert target[2, lower, 1] - target[2, upper, 1] == pytest.approx(0.0, abs=1e-9)  # not crossed
    np.testing.assert_allclose(close_no_further(puppet_neutral), puppet_neutral)


def test_retarget_widen_face_lifts_the_lids_by_the_faces_scale_and_still_closes_them():
    """``widen="face"``: eyes 30 % smaller than the driver's on a face of the same size. The driver's lids
    parting 2 px wider part the puppet's 2 px wider (by "opening", 1.4 px); the driver's blink still just
    closes the puppet's eyes, and an eye that moves up as a whole does not open (a pair that moves together
    takes the eye ratio as a whole)."""
    driver_neutral = generic_template().landmarks3d[list(IDX49), :2]
    puppet_neutral = driver_neutral.copy()
    for upper, lower in FACING[:4]:
        middle, half = (driver_neutral[upper, 1] + driver_neutral[lower, 1]) / 2, (driver_neutral[lower, 1] - driver_neutral[upper, 1]) / 2
        puppet_neutral[upper, 1], puppet_neutral[lower, 1] = middle - 0.7 * half, middle + 0.7 * half
    wide, blink, raised = driver_neutral.copy(), driver_neutral.copy(), driver_neutral.copy()
    for upper, lower in FACING[:4]:
        wide[upper, 1] -= 1.0
        wide[lower, 1] += 1.0
        blink[upper, 1] = blink[lower, 1]
        raised[[upper, lower], 1] -= 2.0
    frames = np.stack([wide, blink, raised])
    opening, face = (retarget(frames, driver_neutral, puppet_neutral, widen=w) for w in ("opening", "face"))
    parted = lambda t: eye_opening(t) - eye_opening(puppet_neutral)
    assert parted(opening[0]) == pytest.approx(1.4) and parted(face[0]) == pytest.approx(2.0)
    np.testing.assert_allclose(face[1:], opening[1:])
    assert eye_opening(face[1]) == pytest.approx(0.0, abs=1e-9) and parted(face[2]) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="widen"):
        retarget(frames, driver_neutral, puppet_neutral, widen="wide")


def test_retarget_lips_closed_closes_a_puppet_whose_mean_mouth_is_open():
    """A puppet whose mean mouth is 6 px open (a collection of people talking), a driver whose rest is
    closed: with the paper's offsets ("mean") the puppet's lips stay 6 px apart when the driver's
    close; with lips "closed" they close, and the driver's 5 px opening gives the puppet its own
    proportion of 5 px; each lip keeps its thickness."""
    driver_neutral = generic_template().landmarks3d[list(IDX49), :2].copy()
    for upper, lower in FACING[4:]:
        driver_neutral[lower, 1] = driver_neutral[upper, 1]  # the driver's lips at rest: closed
    puppet_neutral = driver_neutral * [1.0, 1.1] + [3.0, -2.0]  # a face 10 % longer, elsewhere
    puppet_neutral[list(UPPER_LIP), 1] -= 3.0
    puppet_neutral[list(LOWER_LIP), 1] += 3.0
    assert lip_gap(puppet_neutral) == pytest.approx(6.0)
    opened = driver_neutral.copy()
    opened[list(LOWER_LIP), 1] += 5.0  # the driver's jaw drops 5 px
    sy = eye_mouth_scale(puppet_neutral)[1] / eye_mouth_scale(driver_neutral)[1]
    frames = np.stack([driver_neutral, opened])
    paper = retarget(frames, driver_neutral, puppet_neutral)
    np.testing.assert_allclose(lip_gap(paper), [6.0, 6.0 + 5.0 * sy], atol=1e-9)
    closed = retarget(frames, driver_neutral, puppet_neutral, lips="closed")
    np.testing.assert_allclose(lip_gap(closed), [0.0, 5.0 * sy], atol=1e-9)
    thickness = (lambda f: f[..., UPPER_LIP[5:], 1] - f[..., UPPER_LIP[1:4], 1])  # inner 61-63 below outer 50-52
    np.testing.assert_allclose(thickness(closed), thickness(paper), atol=1e-9)
    np.testing.assert_allclose(np.delete(closed, UPPER_LIP + LOWER_LIP, axis=1),
                               np.delete(paper, UPPER_LIP + LOWER_LIP, axis=1))  # nothing else moves
    with pytest.raises(ValueError, match="lips"):
        retarget(frames, driver_neutral, puppet_neutral, lips="open")


def test_retarget_lips_parted_opens_a_puppet_whose_mean_mouth_is_more_closed_than_the_drivers():
    """A driver who smiles through most of a clip, its mean mouth 8 px open, and a puppet whose mean
    mouth is 2 px open: the paper's offsets ("mean") shut the puppet's lips as soon as the driver's
    are under 6 px apart, so its 4 px opening gives the puppet nothing; "parted" gives the puppet
    the driver's own gap in its proportion (as "closed"), and leaves alone a puppet whose mean mouth
    is the more open (as "mean")."""
    def open_by(face, px):  # each inner lip point `px` below the one facing it
        for upper, lower in FACING[4:]:
            face[lower, 1] = face[upper, 1] + px
        return face

    driver_neutral = open_by(generic_template().landmarks3d[list(IDX49), :2].copy(), 8.0)  # the driver's mean
    puppet_neutral = open_by(driver_neutral * [1.0, 1.1] + [3.0, -2.0], 2.0)  # the puppet's: 2 px
    sy = eye_mouth_scale(puppet_neutral)[1] / eye_mouth_scale(driver_neutral)[1]
    frames = np.stack([driver_neutral + 0.0, driver_neutral + 0.0, driver_neutral + 0.0])
    for frame, gap_px in zip(frames, (0.0, 4.0, 12.0)):
        frame[list(LOWER_LIP), 1] += gap_px - 8.0
    np.testing.assert_allclose(lip_gap(retarget(frames, driver_neutral, puppet_neutral)),
                               [0.0, 0.0, 2.0 + 4.0 * sy], atol=1e-9)
    parted = retarget(frames, driver_neutral, puppet_neutral, lips="parted")
    np.testing.assert_allclose(lip_gap(parted), [0.0, 4.0 * sy, 12.0 * sy], atol=1e-9)
    np.testing.assert_allclose(parted, retarget(frames, driver_neutral, puppet_neutral, lips="closed"))
    wide = open_by(puppet_neutral.copy(), 14.0)  # a puppet whose mean mouth is 14 px open: the paper's offsets
    np.testing.assert_allclose(retarget(frames, driver_neutral, wide, lips="parted"),
                               retarget(frames, driver_neutral, wide))
