"""Deformation transfer with magnitude adjustment (paper Sec. 4, ALGORITHMS §10) on synthetic
ground truth: ``make_face(identity, e).verts`` are the true meshes of every identity and
expression, on the same canonical grid."""

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.interpolate import RBFInterpolator
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

import persona.plugins.face.transfer as transfer_module
from persona.plugins.builtin.denoise import HuberROFDenoise, NoDenoise
from persona.plugins.face.synthetic import Expression, make_face
from persona.plugins.face.template import (
    CENTER_X,
    IDX49,
    CENTER_Y,
    UNIT,
    FaceIdentity,
    face_landmarks_normalised,
    face_normals,
    generic_template,
)
from persona.plugins.face.transfer import (DeformationTransfer, FiducialFollow, TransferParams, grid_normals,
                                           transfer_sequence)
from persona.plugins.face.warp import FACING, retarget

H, W = 244, 194


def _identity_grid():
    yy, xx = np.mgrid[0:H, 0:W]
    return np.stack([xx, yy], axis=-1).astype(np.float64)


def _flat_face():
    """The generic template's fiducials (49, 2), a mask 10 px in from the grid's edge and a flat mesh at rest."""
    fiducials = generic_template().fiducials3d[:, :2]
    mask = np.zeros((H, W), bool)
    mask[10:-10, 10:-10] = True
    mesh = np.dstack([_identity_grid(), np.zeros((H, W))])
    mesh[~mask] = np.nan
    return fiducials, mask, mesh


def _landmark_phi(puppet: FaceIdentity, driver: FaceIdentity) -> np.ndarray:
    """φ: a thin-plate spline through the neutral landmarks, puppet (x, y) -> driver (x, y)."""
    def px(identity):
        lm = face_landmarks_normalised(identity)
        return np.c_[lm[:, 0] * UNIT + CENTER_X, lm[:, 1] * UNIT + CENTER_Y]

    grid = _identity_grid().reshape(-1, 2)
    return RBFInterpolator(px(puppet), px(driver), kernel="thin_plate_spline")(grid).reshape(H, W, 2)


def _rms(a, b, where):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1)[where])))


#: a short "video": every expression of the synthetic face, alone and mixed
SELF_EXPRESSIONS = [Expression(), Expression(smile=0.8), Expression(open=0.8), Expression(brow=0.8),
                    Expression(blink=0.6), Expression(smile=-0.5, brow=-0.4), Expression(smile=0.5, open=0.4, blink=0.8),
                    Expression(open=-1.0)]


@pytest.fixture(scope="module")
def self_sequence():
    identity = FaceIdentity.random(np.random.default_rng(1))
    meshes = np.stack([make_face(identity, e).verts for e in SELF_EXPRESSIONS])
    return meshes, make_face(identity).vert_mask


def test_driver_is_sampled_bilinearly_at_phi():
    """D̄(q) = M̄_D(φ(q)) as scipy's map_coordinates(order=1); φ off the grid or into the driver
    mask's holes makes the pixel invalid."""
    rng = np.random.default_rng(0)
    h, w = 40, 30
    driver = rng.normal(size=(h, w, 3)) * 5 + 100
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).astype(float)
    phi = grid + rng.uniform(-3, 3, (h, w, 2))
    dmask = np.ones((h, w), bool)
    dmask[10:14, 10:14] = False
    driver[~dmask] = np.nan  # must not leak into the samples
    t = DeformationTransfer(driver, phi, driver, np.ones((h, w), bool), dmask, params={"method": "naive"})
    x, y = phi[..., 0], phi[..., 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    near_hole = (x > 8.999) & (x < 14.001) & (y > 8.999) & (y < 14.001)
    assert np.array_equal(t.valid & inside, t.valid)
    assert not np.any(t.valid & near_hole & ~((np.floor(x) == 9) | (np.floor(y) == 9) | (x >= 14) | (y >= 14)))
    assert t.valid.sum() > 0.7 * h * w
    expect = np.stack([map_coordinates(driver[..., c], [y[t.valid], x[t.valid]], order=1, mode="nearest")
                       for c in range(3)], axis=-1)
    np.testing.assert_allclose(t.driver_at_phi, expect, rtol=0, atol=1e-9)


def test_grid_normals_match_the_analytic_template():
    identity = FaceIdentity.random(np.random.default_rng(5))
    face = make_face(identity)
    n = grid_normals(face.verts, face.vert_mask)
    truth = face_normals(identity)
    inner = face.vert_mask & np.isfinite(n[..., 0])
    angle = np.degrees(np.arccos(np.clip(np.sum(n * truth, axis=-1)[inner], -1, 1)))
    assert np.all(n[inner][:, 2] < 0)
    assert np.median(angle) < 0.2 and np.percentile(angle, 99) < 2.0


def test_magnitude_field_follows_the_paper_literally(self_sequence):
    """f = Δ̂·Δ' with Δ' from the nearest driver vertex, computed the obvious way (every point
    queried, φ sampled with map_coordinates) equals the transfer's f, which queries only the
    points that can reach another vertex."""
    meshes, mask = self_sequence
    rng = np.random.default_rng(2)
    phi = _identity_grid() + 0.4 * np.sin(_identity_grid()[..., ::-1] / 9.0) + rng.uniform(-0.05, 0.05, (H, W, 2))
    mean = meshes.mean(axis=0)
    puppet = mean + np.array([0.0, 0.0, 3.0]) + 0.02 * rng.normal(size=mean.shape)
    t = DeformationTransfer(mean, phi, puppet, mask, mask, denoiser=NoDenoise(),
                            params={"method": "magnitude", "small_motion": 0.0})
    frame = t.apply(meshes[6])
    valid = t.valid
    coords = [phi[..., 1][valid], phi[..., 0][valid]]
    sample = lambda m: np.stack([map_coordinates(m[..., c], coords, order=1) for c in range(3)], -1)  # noqa: E731
    dbar = sample(mean)
    delta = sample(meshes[6]) - dbar
    hit = cKDTree(dbar).query(dbar + delta)[1]
    unit = delta / np.linalg.norm(delta, axis=1, keepdims=True)
    f = np.sum(unit * (puppet[valid][hit] - puppet[valid]), axis=1)
    np.testing.assert_allclose(frame.f[valid], f, atol=1e-9)
    assert np.all(np.isnan(frame.f[~valid]))
    assert np.count_nonzero(np.abs(f) > 1.0) > 1000  # the frame moves (and the test would see a bug)
    np.testing.assert_allclose(frame.displacement[valid], unit * f[:, None], atol=1e-9)  # no denoiser, δ = 0


def test_self_puppetry(self_sequence):
    """Puppet = driver (φ = identity): naive transfer is exact, and so is the ratio form without
    denoising (r = 1 on the same face); with its default denoiser (TV weight 0.3) the ratio form
    errs 0.02 px RMS (measured). The paper's method, with its TV weight 1, is close (ALGORITHMS §15:
    RMS < 0.8 px; measured 0.18-0.56 px per frame, mean 0.33; §10.4 quotes 0.37-0.77); the denoising
    helps it (mean 0.36 without), and the normal-component option of §10.3 is better still
    (0.13-0.38, mean 0.18)."""
    meshes, mask = self_sequence
    mean = meshes.mean(axis=0)
    phi = _identity_grid()
    paper_tv = HuberROFDenoise({"weight": 1.0, "outside": "exclude"})
    runs = {}
    for name, params, denoiser in (("naive", {"method": "naive"}, None),
                                   ("ratio", {}, None),
                                   ("ratio, no denoising", {}, NoDenoise()),
                                   ("paper", {"method": "magnitude"}, paper_tv),
                                   ("paper, no denoising", {"method": "magnitude"}, NoDenoise()),
                                   ("normal", {"method": "normal"}, paper_tv)):
        t = DeformationTransfer(mean, phi, mean, mask, mask, params=params, denoiser=denoiser)
        assert t.valid.sum() == mask.sum()
        runs[name] = np.array([_rms(t(m), m, mask) for m in meshes])
    moving = np.array([_rms(mean, m, mask) for m in meshes])  # no motion: 0.6-2.7 px
    assert runs["naive"].max() < 1e-9
    assert runs["ratio, no denoising"].max() < 1e-9
    assert runs["ratio"].max() < 0.1
    assert runs["paper"].max() < 0.8
    assert np.all(runs["paper"] < 0.6 * moving)
    assert runs["paper"].mean() < runs["paper, no denoising"].mean() - 0.02
    assert runs["normal"].mean() < 0.8 * runs["paper"].mean()


@pytest.mark.parametrize("driver_seed, puppet_seed", [(19, 12), (12, 19)])
@pytest.mark.parametrize("sockets", [False, True])
def test_magnitude_adjustment_beats_naive_on_identity_dependent_blinks(driver_seed, puppet_seed, sockets):
    """Two random identities whose eye openings differ by 40 %; a blink closes each face's own
    eye (an identity-dependent magnitude, ALGORITHMS §10.4), so the driver's Δ is the wrong size
    for the puppet and the paper's adjustment must do better than M_P + Δ against make_face(B, e).

    The paper's construction assumes that the moved vertex lands on the mean surface (Fig. 3).
    The synthetic blink slides the lid in the image plane at constant depth, which in the template's
    deep eye sockets leaves it up to 5 px in front of the surface, and the nearest vertex then
    undershoots. For the paper's method the eye sockets and brow ridges are therefore flattened
    (a_e = a_b = 0), so that the blink slides along the surface as in the paper's figure. The ratio
    form (the default) divides that undershoot out and must beat naive with the sockets too.
    """
    a = FaceIdentity.random(np.random.default_rng(driver_seed))
    b = FaceIdentity.random(np.random.default_rng(puppet_seed))
    assert max(a.eye_h, b.eye_h) / min(a.eye_h, b.eye_h) > 1.35
    if not sockets:
        a, b = (dataclasses.replace(i, a_e=0.0, a_b=0.0) for i in (a, b))
    # a video-like sequence: eyes mostly open, so that the mean mesh has open eyes
    exprs = [Expression(blink=1.0)] + [Expression(smile=0.3 * np.sin(k), brow=0.3 * np.cos(k)) for k in range(7)]
    driver = np.stack([make_face(a, e).verts for e in exprs])
    truth = np.stack([make_face(b, e).verts for e in exprs])
    puppet_mean = truth.mean(axis=0)
    phi = _landmark_phi(b, a)
    pmask, dmask = make_face(b).vert_mask, make_face(a).vert_mask
    errors = {}
    paper_tv = HuberROFDenoise({"weight": 1.0, "outside": "exclude"})
    for method in ("naive", "magnitude", "ratio"):
        t = DeformationTransfer(driver.mean(axis=0), phi, puppet_mean, pmask, dmask, params={"method": method},
                                denoiser=paper_tv if method == "magnitude" else None)
        out = t(driver[0])
        moving = t.valid & (np.linalg.norm(truth[0] - puppet_mean, axis=-1) > 1.0)  # the eyelids
        assert moving.sum() > 300
        errors[method] = (_rms(out, truth[0], t.valid), _rms(out, truth[0], moving))
    print(f"\n{driver_seed} -> {puppet_seed}, sockets {sockets}, RMS px (face, moving eyelids): "
          + ", ".join(f"{k} {v[0]:.2f} / {v[1]:.2f}" for k, v in errors.items()))
    # measured (whole face / moving eyelids), flattened: 19 -> 12: naive 0.15 / 1.03 px, paper
    # 0.05 / 0.34, ratio 0.05 / 0.31; 12 -> 19: naive 0.17 / 1.10, paper 0.12 / 0.75, ratio 0.09 / 0.59.
    # With the template's eye sockets kept, 19 -> 12 the paper's still wins (0.10 / 0.68) but
    # 12 -> 19 it loses (0.21 / 1.29); the ratio form wins both (0.05 / 0.35, 0.10 / 0.61)
    assert errors["ratio"][1] < 0.8 * errors["naive"][1], errors
    assert errors["ratio"][0] < errors["naive"][0], errors
    if not sockets:
        assert errors["magnitude"][1] < 0.8 * errors["naive"][1], errors
        assert errors["magnitude"][0] < errors["naive"][0], errors


def test_the_kd_tree_is_built_once_per_sequence(self_sequence, monkeypatch):
    meshes, mask = self_sequence
    built = []

    class CountingTree(cKDTree):
        def __init__(self, *args, **kwargs):
            built.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(transfer_module, "cKDTree", CountingTree)
    t = DeformationTransfer(meshes.mean(axis=0), _identity_grid(), meshes.mean(axis=0), mask, mask)
    for m in meshes[:3]:
        t(m)
    assert len(built) == 1


def test_invalid_pixels_stay_put(self_sequence):
    meshes, mask = self_sequence
    mean = meshes.mean(axis=0)
    phi = _identity_grid()
    phi[:120, :, 0] += 500.0  # the top half points off the driver's grid
    frame_mesh = meshes[1].copy()
    frame_mesh[200:210, 90:100] = np.nan  # a frame with a hole: no data there, no motion
    t = DeformationTransfer(mean, phi, mean, mask, mask)
    assert not t.valid[:120].any() and np.array_equal(t.valid[120:], mask[120:])
    frame = t.apply(frame_mesh)
    assert np.array_equal(frame.mesh[~t.valid], mean[~t.valid], equal_nan=True)
    hole = np.zeros((H, W), bool)
    hole[201:209, 91:99] = True  # the hole's interior (its rim interpolates towards it)
    assert np.all(frame.displacement[hole] == 0.0)
    assert np.all(np.isfinite(frame.mesh[t.valid]))
    assert np.all(np.isfinite(frame.f_star[t.valid]))


def test_transfer_sequence_uses_the_sequence_mean(self_sequence):
    meshes, mask = self_sequence
    out = transfer_sequence(meshes, _identity_grid(), meshes.mean(axis=0), mask, mask, params={"method": "naive"})
    assert out.shape == meshes.shape
    assert np.abs(out - meshes)[:, mask].max() < 1e-9


def test_exclude_and_inpaint_agree_on_the_valid_pixels(self_sequence):
    """The transfer's default denoiser leaves the pixels without data out of the problem
    (outside='exclude'); inpainting them (ALGORITHMS §10.2's reading), solved to convergence,
    gives nearly the same f* (measured 0.03 px RMS on this frame, 0.01-0.03 on the others) and
    the same transfer error (to 0.002 px)."""
    meshes, mask = self_sequence
    mean = meshes.mean(axis=0)
    frames = {}
    for outside, extra in (("exclude", {}), ("inpaint", {"tol": 0.0, "iterations": 5000})):
        t = DeformationTransfer(mean, _identity_grid(), mean, mask, mask,
                                denoiser=HuberROFDenoise({"outside": outside, **extra}))
        frames[outside] = t.apply(meshes[2])
    a, b = frames["exclude"], frames["inpaint"]
    assert np.sqrt(np.mean((a.f_star[mask] - b.f_star[mask]) ** 2)) < 0.04
    assert abs(_rms(a.mesh, meshes[2], mask) - _rms(b.mesh, meshes[2], mask)) < 0.005


def test_params_and_inputs_are_checked(self_sequence):
    meshes, mask = self_sequence
    with pytest.raises(ValidationError):
        TransferParams(method="scaled")
    with pytest.raises(ValidationError):
        TransferParams(small_motion=-1.0)
    mean = meshes.mean(axis=0)
    with pytest.raises(ValueError):
        DeformationTransfer(mean, _identity_grid()[:-1], mean, mask, mask)
    with pytest.raises(TypeError):
        DeformationTransfer(mean, _identity_grid(), mean, mask.astype(np.uint8), mask)
    t = DeformationTransfer(mean, _identity_grid(), mean, mask, mask, params={"method": "naive"})
    with pytest.raises(ValueError):
        t(meshes[0][:-1])


def test_fiducial_follow_lands_the_fiducials_and_holds_the_rim():
    """On a flat face, misses of a few px at the fiducials are taken out to a quarter of a pixel by
    the default spline (λ 0.1), the rim of the mask does not move, weight 0 moves nothing and a
    target with a NaN moves nothing at its fiducial."""
    fiducials, mask, mesh = _flat_face()
    follow = FiducialFollow(fiducials, mask)
    np.testing.assert_allclose(follow.landmarks(mesh), fiducials, atol=1e-4)
    offsets = np.zeros((49, 2))
    offsets[19:31, 1] = [0, 3, 3, 0, 0, 0, 0, 3, 3, 0, 0, 0]  # the upper lids down 3 px
    offsets[31:, 1] = 2.0 * np.sign(fiducials[31:, 1] - fiducials[31:, 1].mean())  # the lips part
    moved = follow(mesh, fiducials + offsets)
    assert np.abs(follow.landmarks(moved) - (fiducials + offsets)).max() < 0.25
    rim = mask.copy()
    rim[11:-11, 11:-11] = False  # the mask's outermost ring
    assert np.abs(moved[rim] - mesh[rim]).max() < 0.1
    assert np.isnan(moved[~mask]).all()
    np.testing.assert_allclose(follow(mesh, fiducials + offsets, 0.0), mesh)
    target = fiducials + offsets
    target[20] = np.nan
    assert np.abs(follow.landmarks(follow(mesh, target))[20] - fiducials[20]).max() < 0.5


def test_the_lips_of_a_shut_mouth_part_as_far_as_their_targets_with_split_lips():
    """A puppet whose photos keep the mouth shut has its inner lips half a texel apart. Targets open them by 14 px
    (the upper lip up 6, the lower down 8, the outer lower lip with it). With ``split_lips`` each inner lip, read on
    the first texel row wholly on its own side of the line where they meet (own_sides), lands within a quarter of a
    pixel of its target, and so does every other fiducial; the texel row on that line is the only one between
    the lips, and the rows under the lower lip drop as it does. The spline alone, which cannot move points so
    close so far apart, misses by 2 px and swings past: the rows under the lower lip drop 14 px for its 8. Lips
    already further apart are read where they are."""
    fiducials, mask, mesh = _flat_face()
    inner = [IDX49.index(i) for i in (61, 62, 63, 65, 66, 67)]
    shut = fiducials.copy()
    for upper, lower in FACING[4:]:
        middle = (shut[upper, 1] + shut[lower, 1]) / 2
        shut[upper, 1], shut[lower, 1] = middle - 0.25, middle + 0.25
    offsets = np.zeros((49, 2))
    offsets[[IDX49.index(i) for i in (49, 50, 51, 52, 53, 61, 62, 63)], 1] = -6.0
    offsets[[IDX49.index(i) for i in (55, 56, 57, 58, 59, 65, 66, 67)], 1] = 8.0
    target = shut + offsets
    read = transfer_module.own_sides(shut)
    np.testing.assert_array_equal(np.delete(read, inner, axis=0), np.delete(shut, inner, axis=0))
    for upper, lower in FACING[4:]:
        assert read[lower, 1] - read[upper, 1] <= 2 and read[upper, 1] == np.floor(read[upper, 1])
    np.testing.assert_array_equal(transfer_module.own_sides(fiducials), fiducials)  # the template's lips: apart

    def gap(landmarks):
        return np.mean([landmarks[lower, 1] - landmarks[upper, 1] for upper, lower in FACING[4:]])

    split = FiducialFollow(shut, mask, split_lips=True)
    moved = split(mesh, target)
    landed = split.moved(moved, read) - (read - shut)  # each fiducial where its own side's texel went
    assert np.abs(landed - target).max() < 0.25
    assert gap(target) - gap(shut) == pytest.approx(14.0)
    column = int(round(shut[IDX49.index(66), 0]))
    under = np.arange(int(read[IDX49.index(66), 1]), int(shut[IDX49.index(57), 1]))  # the lower lip's rows
    np.testing.assert_allclose(moved[under, column, 1] - under, 8.0, atol=0.25)
    alone = FiducialFollow(shut, mask)(mesh, target)
    assert np.abs(split.moved(alone, read) - (read - shut) - target).max() > 1.5
    assert (alone[under, column, 1] - under).max() > 12.0


def _narrowing_mouth(beyond: float):
    """The generic template's fiducials, a face mask, and a transferred mesh whose mouth narrows (the
    corners 4 px inwards) with a sideways motion ``beyond`` times the corners' 10 px beyond them (0.5: the
    transfer's on Obama's narrow mouths; 1.5: an "O" whose cheeks come in further than its corners)."""
    fiducials = generic_template().fiducials3d[:, :2]
    mask = np.zeros((H, W), bool)
    mask[10:-10, 10:-10] = True
    left, right = fiducials[31], fiducials[37]  # iBUG 48 and 54
    centre, half = (left + right) / 2, (right[0] - left[0]) / 2
    grid = _identity_grid()
    u = np.abs(grid[..., 0] - centre[0])
    share = np.where(u <= half, u / half, np.clip(1 + (beyond - 1) * (u - half) / 10, 0, max(1.0, beyond)))
    dx = -4.0 * np.sign(grid[..., 0] - centre[0]) * share * np.exp(-((grid[..., 1] - centre[1]) / 15) ** 2)
    mesh = np.dstack([grid[..., 0] + dx, grid[..., 1], np.zeros((H, W))])
    mesh[~mask] = np.nan
    return fiducials, mask, mesh


def test_corner_reach_moves_the_skin_beyond_a_mouth_corner_sideways_with_it():
    """A transferred mesh whose mouth narrows (the corners 4 px inwards) but whose sideways motion
    falls to half 10 px beyond the corners, as the transfer's does on real drives, its fiducials
    already on their targets: without ``corner_reach`` the follower leaves that skin where it is
    (2 px); with a reach of 30 px it moves the corner's 4 px less a third of the difference
    (3.33 px, within 0.3). The fiducials stay on their targets, and the brows do not move."""
    fiducials, mask, mesh = _narrowing_mouth(0.5)
    left = fiducials[31]
    out = left - np.array([10.0, 0.0])  # 10 px beyond the left corner
    brow = np.array([left[0], fiducials[:10, 1].mean()])
    for corner_reach, expected in ((0.0, 2.0), (30.0, 4.0 - 2.0 / 3)):
        follow = FiducialFollow(fiducials, mask, corner_reach=corner_reach)
        target = follow.landmarks(mesh)
        moved = follow(mesh, target)
        assert np.abs(follow.landmarks(moved) - target).max() < 0.25, corner_reach
        assert follow.moved(moved, out[None])[0, 0] - out[0] == pytest.approx(expected, abs=0.3), corner_reach
        assert np.abs(follow.moved(moved, brow[None])[0] - follow.moved(mesh, brow[None])[0]).max() < 0.3, corner_reach


def test_brow_hold_keeps_the_brow_where_it_is_as_the_lids_shut():
    """The upper lids come down onto the lower ones (6 px), the brows stay: on its own the follower
    drags the skin half-way up to the brows down with the lids (5 px), with ``brow_hold`` 0.5 that skin
    stays within 0.3 px; the brows stay within 0.5 px and the fiducials land on their targets either way."""
    fiducials, mask, mesh = _flat_face()
    target = fiducials.copy()
    for upper, lower in (((20, 21), (24, 23)), ((26, 27), (30, 29))):  # iBUG 37, 38 onto 41, 40; 43, 44 onto 47, 46
        target[list(upper), 1] = fiducials[list(lower), 1] - 0.5
    lids = fiducials[[20, 21, 26, 27]]
    brows = np.array([[x, np.interp(x, *fiducials[side][np.argsort(fiducials[side][:, 0])].T)]
                      for x, side in zip(lids[:, 0], (slice(0, 5),) * 2 + (slice(5, 10),) * 2)])
    between = lids + 0.5 * (brows - lids)
    for hold, dragged in ((0.0, True), (0.5, False)):
        follow = FiducialFollow(fiducials, mask, brow_hold=hold)
        moved = follow(mesh, target)
        assert np.abs(follow.landmarks(moved) - target).max() < 0.25, hold
        shift = np.abs(follow.moved(moved, between) - between).max()
        assert (shift > 4.0) if dragged else (shift < 0.3), (hold, shift)
        assert np.abs(follow.moved(moved, brows) - brows).max() < 0.5, hold


def test_brow_hold_leaves_eyes_that_do_not_shut():
    """Brows up 2 px and the upper lids up 3 (the eyes widen), or the lids 0.3 px down of the 6.5 px they
    are apart with the brows still (the hold starts at a tenth): ``brow_hold`` moves the mesh exactly as
    the follower alone does (to 1e-6 px)."""
    fiducials, mask, mesh = _flat_face()
    for brows, lids in ((-2.0, -3.0), (0.0, 0.3)):
        target = fiducials.copy()
        target[:10, 1] += brows
        target[[20, 21, 26, 27], 1] += lids
        moved = [FiducialFollow(fiducials, mask, brow_hold=hold)(mesh, target) for hold in (0.0, 0.5)]
        np.testing.assert_allclose(moved[1], moved[0], atol=1e-6, err_msg=f"brows {brows}, lids {lids}")


def test_corner_reach_leaves_skin_that_already_moves_further_than_the_corner():
    """An "O" whose cheeks come in further than the mouth's corners (the transfer's sideways motion 1.5
    times the corners' 10 px beyond them, as on Powell <- woman), the corners' targets 2 px lower: with a
    reach of 30 px the follower moves the whole mesh as it does without one (to 1e-6 px), sideways and
    down; the reach only ever carries skin further the corner's way."""
    fiducials, mask, mesh = _narrowing_mouth(1.5)
    moved = []
    for corner_reach in (0.0, 30.0):
        follow = FiducialFollow(fiducials, mask, corner_reach=corner_reach)
        target = follow.landmarks(mesh)
        target[[31, 37], 1] += 2.0
        moved.append(follow(mesh, target))
    np.testing.assert_allclose(moved[1], moved[0], atol=1e-6)


@pytest.mark.parametrize("driver_seed, puppet_seed", [(19, 12), (12, 19)])
def test_fiducial_follow_closes_the_puppets_blink(driver_seed, puppet_seed):
    """The driver's full blink closes the puppet's own eye, whose opening differs by 40 %: after the
    transfer the puppet's lids are still apart; following the retargeted fiducials closes them to
    within 0.3 px of the ground truth make_face(B, blink=1)."""
    a = FaceIdentity.random(np.random.default_rng(driver_seed))
    b = FaceIdentity.random(np.random.default_rng(puppet_seed))
    exprs = [Expression(blink=1.0)] + [Expression(smile=0.3 * np.sin(k), brow=0.3 * np.cos(k)) for k in range(7)]
    driver = np.stack([make_face(a, e).verts for e in exprs])
    truth = make_face(b, exprs[0])
    puppet_mean = np.stack([make_face(b, e).verts for e in exprs]).mean(axis=0)
    pmask = make_face(b).vert_mask
    texels = make_face(b).landmarks3d[list(IDX49), :2]  # B's neutral fiducials on the parameter grid
    follow = FiducialFollow(texels, pmask)
    seen = np.stack([make_face(a, e).landmarks3d[list(IDX49), :2] for e in exprs])  # the driver's landmarks
    target = retarget(seen, seen.mean(axis=0), follow.landmarks(puppet_mean))[0]
    t = DeformationTransfer(driver.mean(axis=0), _landmark_phi(b, a), puppet_mean, pmask, make_face(a).vert_mask)
    transferred = t(driver[0])
    followed = follow(transferred, target)

    def lids(mesh):  # the four upper-to-lower lid gaps, px
        points = follow.landmarks(mesh)
        return np.array([points[lower, 1] - points[upper, 1] for upper, lower in FACING[:4]])

    truth_gaps = truth.landmarks3d[list(IDX49), 1][[lo for _, lo in FACING[:4]]] - \
        truth.landmarks3d[list(IDX49), 1][[up for up, _ in FACING[:4]]]
    print(f"\n{driver_seed} -> {puppet_seed}: lid gaps, truth {truth_gaps.round(2)}, transfer "
          f"{lids(transferred).round(2)}, followed {lids(followed).round(2)}")
    assert np.abs(lids(followed) - truth_gaps).max() < 0.3
    assert np.abs(lids(transferred) - truth_gaps).mean() > np.abs(lids(followed) - truth_gaps).mean()


def _template_at_rest():
    """The generic template's mask and fiducials, its mesh (x, y, depth) where nothing has moved, and the part
    of it below the mouth's middle (transfer.below_mouth)."""
    template = generic_template()
    mask, fiducials = template.mask, template.fiducials3d[:, :2]
    ys, xs = np.mgrid[0:mask.shape[0], 0:mask.shape[1]].astype(np.float64)
    return mask, fiducials, np.stack([xs, ys, template.depth], axis=-1), transfer_module.below_mouth(mask, fiducials)


def test_a_mesh_folded_below_the_mouth_is_unfolded_and_nothing_else_moves():
    """A lower lip dropped 6 px over the skin under it: after `unfolded`, the rows below the mouth follow
    one another at least `step` px apart, the lip's rows keep their drop, the skin it folded over is
    squeezed into a band under it (laid flat with step 0), the rows below where the column runs lower
    again, those above the mouth, x and depth are untouched; a mesh without a fold is returned as it was,
    and so is one squeezed to 0.1 px a row without folding."""
    mask, fiducials, mesh, below = _template_at_rest()
    top = int(np.ceil(fiducials[[IDX49.index(62), IDX49.index(66)], 1].mean()))  # the mouth's middle
    assert not below[:top].any() and below[top:].sum() == mask[top:].sum()
    np.testing.assert_array_equal(transfer_module.unfolded(mesh, below), mesh)
    pressed = mesh.copy()
    pressed[top:top + 20, :, 1] = top + 0.1 * np.arange(20)[:, None]  # 20 rows within 2 px, then a jump
    np.testing.assert_array_equal(transfer_module.unfolded(pressed, below), pressed)

    lip = top + 4  # the lower lip's rows: 4 below the mouth's middle, 4 rows thick
    folded = mesh.copy()
    folded[lip:lip + 4, :, 1] += 6.0  # dropped 6 px: over the next rows, which have not moved
    col = int(fiducials[:, 0].mean())
    for step, caught_up in ((0.3, lip + 12), (0.0, lip + 10)):  # where y = row meets the lip's last + step a row
        out = transfer_module.unfolded(folded, below, step)
        steps = np.diff(np.where(below, out[..., 1], np.nan), axis=0)
        assert np.nanmin(steps) >= step - 1e-9
        np.testing.assert_array_equal(out[lip:lip + 4], folded[lip:lip + 4])  # the lip keeps its drop
        squeezed = folded[lip + 3, col, 1] + step * np.arange(1, caught_up - lip - 3)
        np.testing.assert_allclose(out[lip + 4:caught_up, col, 1], squeezed)  # the band under the lip
        np.testing.assert_array_equal(out[caught_up:, col, 1], folded[caught_up:, col, 1])  # as it was
        np.testing.assert_array_equal(out[:lip], folded[:lip])
        np.testing.assert_array_equal(out[..., [0, 2]], folded[..., [0, 2]])


def test_a_lower_lip_hanging_below_its_own_edge_is_spread_between_its_edges():
    """The lower lip's body runs from B's inner lower lip (through iBUG 67-65) to its outer edge (through 59-55,
    which the follower put on their targets). Its middle rows dropped 6 px, below the outer edge: with `lip`, the
    lip's rows are spread evenly between its two edges, which stay where they were, as do the chin under it and
    the rows above; the lip is then drawn as the texture has it (here: back at rest). Without `lip`, the edge
    and the chin are pushed down instead (the lip drawn taller than its target)."""
    mask, fiducials, mesh, below = _template_at_rest()
    lip = transfer_module.lower_lip(below, fiducials)
    x, y = fiducials[IDX49.index(57)]
    col = int(round(x))
    inner, outer = lip[:, col]
    assert fiducials[IDX49.index(66), 1] - 1 < inner < outer <= y + 1
    corners = fiducials[[IDX49.index(48), IDX49.index(54)], 0]
    left, right = int(np.floor(corners.min())), int(np.ceil(corners.max()))
    assert np.isnan(lip[:, :left]).all() and np.isnan(lip[:, right + 1:]).all()
    np.testing.assert_allclose(transfer_module.unfolded(mesh, below, lip=lip), mesh, atol=1e-9)  # at rest: as it was

    top, edge = int(np.ceil(inner)), int(np.floor(outer))
    hanging = mesh.copy()
    for c in np.flatnonzero(np.isfinite(lip[0])):  # the lip's middle rows dropped below its edge
        hanging[int(np.ceil(lip[0, c])) + 1:int(np.floor(lip[1, c])), c, 1] += 6.0
    step = 0.3
    out = transfer_module.unfolded(hanging, below, step, lip=lip)
    steps = np.diff(np.where(below, out[..., 1], np.nan), axis=0)
    assert np.nanmin(steps) >= step - 1e-9
    np.testing.assert_array_equal(out[edge + 1:, col], hanging[edge + 1:, col])  # the chin stays
    np.testing.assert_allclose(out[top:edge + 1, col], mesh[top:edge + 1, col], atol=1e-9)  # spread: back at rest
    np.testing.assert_array_equal(out[:top, col], hanging[:top, col])
    np.testing.assert_array_equal(out[~below], hanging[~below])
    np.testing.assert_array_equal(out[..., [0, 2]], hanging[..., [0, 2]])
    pushed = transfer_module.unfolded(hanging, below, step)
    assert pushed[edge, col, 1] > hanging[edge, col, 1] + 3  # without `lip`: the edge pushed off its place


def test_the_built_in_transfer_backend_is_the_transfer_the_follower_and_the_unfolding():
    """The ``transfer`` kind's default (plugins/builtin/transfer.py) prepares, once, the deformation transfer,
    the fiducial follower on the targets smoothed in time and the unfolding below the mouth, with its params;
    its cache key is the motion stage's before the kind existed: "-", and version 8."""
    from persona.plugins.builtin.transfer import DeformationTransferBackend
    from persona.plugins.face.dynamics import smooth_in_time
    from persona.plugins.kinds import MotionPair
    from persona.plugins.manager import default_registry

    assert default_registry().default("transfer") == "deformation"
    assert (DeformationTransferBackend.key_name, DeformationTransferBackend.version) == ("-", "8")
    mask, fiducials, mesh, below = _template_at_rest()
    rng = np.random.default_rng(3)
    targets = fiducials + rng.normal(0, 0.5, (4, 49, 2))
    frames = mesh + np.where(mask[..., None], rng.normal(0, 0.2, (4, *mesh.shape)), 0)
    params = {"fiducial_sigma": 1.0, "corner_reach": 10.0}
    pair = MotionPair(mesh, mesh[..., :2].copy(), mesh, mask, mask, fiducials, targets, NoDenoise())
    made = DeformationTransferBackend(params).prepare(pair)

    p = TransferParams.model_validate(params)
    transfer = DeformationTransfer(mesh, mesh[..., :2], mesh, mask, mask, params=p, denoiser=NoDenoise())
    follow = FiducialFollow(fiducials, mask, lam=p.fiducial_lambda, corner_reach=p.corner_reach,
                            brow_hold=p.brow_hold, split_lips=p.split_lips)
    steady = smooth_in_time(targets, p.fiducial_sigma)
    lip = transfer_module.lower_lip(below, fiducials)
    for t in (0, 3):
        expected = transfer_module.unfolded(follow(transfer(frames[t]), steady[t], p.fiducials), below,
                                            p.unfold_step, lip=lip)
        np.testing.assert_array_equal(made(t, frames[t]), expected)
