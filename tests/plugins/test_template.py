import numpy as np
import pytest

from persona.plugins.face.template import (
    CANONICAL_HEIGHT,
    CANONICAL_WIDTH,
    IDX49,
    MIRROR68,
    FaceIdentity,
    FaceTemplate,
    face_depth,
    face_landmarks3d,
    face_oval,
    generic_template,
)


def test_idx49_is_the_papers_49_fiducials():
    assert len(IDX49) == 49
    assert len(set(IDX49)) == 49
    assert not set(IDX49) & (set(range(17)) | {60, 64})
    assert set(IDX49) | set(range(17)) | {60, 64} == set(range(68))
    assert list(IDX49) == sorted(IDX49)


def test_mirror68_is_an_involution_swapping_sides():
    m = np.array(MIRROR68)
    assert sorted(m) == list(range(68))
    assert np.array_equal(m[m], np.arange(68))
    assert m[36] == 45 and m[39] == 42 and m[48] == 54 and m[0] == 16 and m[30] == 30


def test_shapes_and_dtypes():
    t = generic_template()
    assert isinstance(t, FaceTemplate)
    assert t.depth.shape == (CANONICAL_HEIGHT, CANONICAL_WIDTH) and t.depth.dtype == np.float64
    assert t.mask.shape == (244, 194) and t.mask.dtype == bool
    assert t.normals.shape == (244, 194, 3) and t.normals.dtype == np.float64
    assert t.landmarks3d.shape == (68, 3) and t.landmarks3d.dtype == np.float64
    assert t.fiducials3d.shape == (49, 3)
    assert np.array_equal(t.fiducials3d, t.landmarks3d[list(IDX49)])
    assert np.isfinite(t.depth).all()
    assert generic_template() is t  # cached
    with pytest.raises(ValueError):
        t.depth[0, 0] = 1.0  # shared cached arrays are read-only


def test_nose_tip_is_closest_landmark_and_near_the_depth_minimum():
    t = generic_template()
    assert np.argmin(t.landmarks3d[:, 2]) == 30
    # the surface's closest point on the face is at the nose tip landmark (within 1.5 px)
    i, j = np.unravel_index(np.argmin(np.where(t.mask, t.depth, np.inf)), t.depth.shape)
    assert np.hypot(j - t.landmarks3d[30, 0], i - t.landmarks3d[30, 1]) < 1.5


def test_eye_sockets_are_deeper_than_brows_and_nose():
    t = generic_template()
    lm = t.landmarks3d
    eye_z = lm[36:48, 2].mean()
    assert eye_z > lm[17:27, 2].mean()
    assert eye_z > lm[27:31, 2].max()


def test_generic_template_is_symmetric():
    t = generic_template()
    lm = t.landmarks3d
    mirrored = lm[list(MIRROR68)].copy()
    mirrored[:, 0] = 2 * 97.0 - mirrored[:, 0]
    np.testing.assert_allclose(mirrored, lm, atol=1e-9)
    # depth map symmetric about x = 97 (columns 0..194 -> 194-j; column 97 is the axis)
    d = t.depth[:, 1:]
    np.testing.assert_allclose(d, d[:, ::-1], atol=1e-9)
    assert np.array_equal(t.mask[:, 1:], t.mask[:, 1:][:, ::-1])


def test_layout_is_anatomical():
    lm = generic_template().landmarks3d
    y = lm[:, 1]
    assert y[17:27].mean() < y[36:48].mean() < y[30] < y[33] < y[51] < y[57] < y[8]
    er, el = lm[36:42, :2].mean(0), lm[42:48, :2].mean(0)
    assert er[0] < 97 < el[0]  # subject's right eye on the image left
    np.testing.assert_allclose(el - er, [0.82 * 80, 0.0], atol=0.1)


def test_landmarks_and_mask_inside_frame():
    for t in (generic_template(), FaceTemplate.from_identity(FaceIdentity.random(np.random.default_rng(3)))):
        x, y = t.landmarks3d[:, 0], t.landmarks3d[:, 1]
        assert (x >= 0).all() and (x <= CANONICAL_WIDTH - 1).all()
        assert (y >= 0).all() and (y <= CANONICAL_HEIGHT - 1).all()
        # the oval does not touch the frame border
        assert not t.mask[0].any() and not t.mask[-1].any()
        assert not t.mask[:, 0].any() and not t.mask[:, -1].any()


def test_mask_covers_landmarks_jaw_on_the_boundary():
    t = generic_template()
    ij = np.round(t.landmarks3d[:, :2]).astype(int)
    assert t.mask[ij[17:, 1], ij[17:, 0]].all()
    X = (t.landmarks3d[:17, 0] - 97) / 80
    Y = (t.landmarks3d[:17, 1] - 112) / 80
    r = face_oval(FaceIdentity(), X, Y)
    assert (r <= 1.0).all() and (r >= 0.93).all()


def test_normals_unit_and_towards_camera():
    t = generic_template()
    n = t.normals[t.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert (n[:, 2] < 0).all()
    # consistent with the depth map's finite differences
    zy, zx = np.gradient(t.depth)
    m = t.mask.copy()
    m[[0, -1], :] = m[:, [0, -1]] = False
    approx = np.stack([zx, zy, -np.ones_like(zx)], -1)
    approx /= np.linalg.norm(approx, axis=-1, keepdims=True)
    cos = (approx[m] * t.normals[m]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 0.5


def test_random_identities_differ_and_stay_in_the_frame():
    rng = np.random.default_rng(0)
    ids = [FaceIdentity.random(rng) for _ in range(20)]
    assert len(set(ids)) == 20
    for ident in ids:
        lm = face_landmarks3d(ident)
        assert np.argmin(lm[:, 2]) == 30
        depth, mask = face_depth(ident)
        assert np.isfinite(depth).all() and mask[1:-1, 1:-1].sum() == mask.sum()


def test_bad_identity_rejected():
    with pytest.raises(ValueError):
        FaceIdentity(fw=1.5)
    with pytest.raises(ValueError):
        FaceIdentity(fh=2.0)


def test_half_resolution_grid_samples_the_same_face():
    full, _ = face_depth(FaceIdentity())
    half, mask = face_depth(FaceIdentity(), 122, 97)
    assert half.shape == (122, 97) and mask.shape == (122, 97)
    np.testing.assert_allclose(half, full[::2, ::2] / 2, atol=1e-9)
    with pytest.raises(ValueError):
        face_depth(FaceIdentity(), 100, 97)
