import cv2
import numpy as np
import pytest

from persona.plugins.face.synthetic import (
    Expression,
    Light,
    SyntheticPhoto,
    expression_field,
    look_at_pose,
    make_collection,
    make_driver_video,
    make_face,
    render_canonical,
    render_photo,
)
from persona.plugins.face.template import (
    BASE_DEPTH,
    FaceIdentity,
    face_height,
    face_landmarks_normalised,
    generic_template,
)


def _canonical_to_camera(p, photo):
    R = cv2.Rodrigues(photo.rvec)[0]
    return p @ R.T + photo.tvec


def _angle_deg(r1, r2):
    R = cv2.Rodrigues(np.asarray(r1, float))[0].T @ cv2.Rodrigues(np.asarray(r2, float))[0]
    return np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def test_neutral_face_is_the_template():
    t = generic_template()
    f = make_face()
    np.testing.assert_allclose(f.depth, t.depth)
    np.testing.assert_array_equal(f.mask, t.mask)
    np.testing.assert_allclose(f.normals, t.normals, atol=1e-6)
    np.testing.assert_allclose(f.landmarks3d, t.landmarks3d)
    assert f.albedo.shape == (244, 194, 3) and f.albedo.min() >= 0 and f.albedo.max() <= 1
    assert f.verts.shape == (244, 194, 3)


def test_orthographic_raycast_depth_equals_analytic():
    f = make_face(FaceIdentity.random(np.random.default_rng(5)))
    r = render_canonical(f)
    inner = f.mask & r["mask"]
    assert inner.sum() > 0.95 * f.mask.sum()
    assert np.abs(r["depth"][inner] - f.depth[inner]).max() < 1e-3
    np.testing.assert_allclose(r["albedo"][inner], f.albedo[inner], atol=1e-5)


def test_perspective_raycast_hits_the_analytic_surface():
    ident = FaceIdentity()
    f = make_face(ident)
    rvec, tvec, K = look_at_pose(20, -10, 5, face_px=150, image_size=(250, 250))
    p = render_photo(f, rvec=rvec, tvec=tvec, camera=K, image_size=(250, 250))
    i, j = np.nonzero(p.face_mask)
    rays = np.stack([j, i, np.ones_like(j)], 1).astype(float) @ np.linalg.inv(K).T
    pts_cam = rays * p.depth[i, j][:, None]
    R = cv2.Rodrigues(rvec)[0]
    pts = (pts_cam - tvec) @ R  # back to canonical (x, y, Z)
    X, Y = (pts[:, 0] - 97) / 80, (pts[:, 1] - 112) / 80
    err = np.abs(pts[:, 2] - (BASE_DEPTH - face_height(ident, X, Y)))
    # piecewise-linear mesh vs the analytic surface: chord error of a 1 px grid
    assert np.median(err) < 0.01 and err.max() < 0.2
    # the uv map points back at the same canonical points (neutral face: verts = (u, v, Z))
    np.testing.assert_allclose(p.uv[i, j], pts[:, :2], atol=1e-3)


@pytest.mark.parametrize("yaw", [0.0, 25.0])
def test_landmarks_are_projections_and_pnp_recovers_pose(yaw):
    f = make_face(FaceIdentity(), Expression())
    rvec, tvec, K = look_at_pose(yaw, 8, -4, face_px=120, image_size=(250, 250))
    p = render_photo(f, rvec=rvec, tvec=tvec, camera=K, image_size=(250, 250))
    proj = cv2.projectPoints(f.landmarks3d, rvec, tvec, K, None)[0].reshape(-1, 2)
    np.testing.assert_allclose(p.landmarks, proj, atol=1e-9)
    ok, r, t = cv2.solvePnP(f.landmarks3d, p.landmarks, K, None, flags=cv2.SOLVEPNP_EPNP)
    ok, r, t = cv2.solvePnP(f.landmarks3d, p.landmarks, K, None, r, t, True, cv2.SOLVEPNP_ITERATIVE)
    assert ok
    assert _angle_deg(r, rvec) < 0.1
    assert np.linalg.norm(t.ravel() - tvec) < 0.5


def test_pose_places_face_centred_at_requested_size():
    f = make_face()
    rvec, tvec, K = look_at_pose(0, 0, 0, face_px=140, image_size=(250, 250))
    p = render_photo(f, rvec=rvec, tvec=tvec, camera=K, image_size=(250, 250))
    cols = np.nonzero(p.face_mask.any(axis=0))[0]
    assert abs((cols[-1] - cols[0] + 1) - 140) < 14
    assert abs((cols[0] + cols[-1]) / 2 - 124.5) < 2
    assert p.visible.all()


def test_visibility_under_strong_yaw():
    f = make_face()
    rvec, tvec, K = look_at_pose(60, 0, 0, face_px=140, image_size=(250, 250))
    p = render_photo(f, rvec=rvec, tvec=tvec, camera=K, image_size=(250, 250))
    assert p.visible[30] and p.visible[33]
    assert not p.visible.all()  # part of the far side is hidden behind the nose or turned away


def test_shading_at_a_frontal_pixel():
    f = make_face()
    light = Light(0.4, (0.3, -0.2, -0.7))
    image_size = (251, 251)
    rvec, tvec, K = look_at_pose(0, 0, 0, face_px=150, image_size=image_size)
    # move the canonical vertex (97, 112) onto the principal ray: the centre pixel ray hits it exactly
    c = f.verts[112, 97]
    tvec = np.array([-c[0], -c[1], tvec[2]])
    p = render_photo(f, rvec=rvec, tvec=tvec, camera=K, light=light, image_size=image_size, background=(0, 0, 0))
    expected = f.albedo[112, 97] * max(0.0, light.ambient + f.normals[112, 97] @ np.array(light.direction))
    np.testing.assert_allclose(p.image[125, 125] / 255.0, expected, atol=0.6 / 255 + 1e-6)
    # rotating the head rotates the light with it: a pixel's shade does not depend on the pose
    rvec2, tvec2, K2 = look_at_pose(20, 0, 0, face_px=150, image_size=image_size)
    p2 = render_photo(f, rvec=rvec2, tvec=tvec2, camera=K2, light=light, image_size=image_size)
    proj = cv2.projectPoints(f.verts[112, 97][None], rvec2, tvec2, K2, None)[0].ravel()
    x, y = np.round(proj).astype(int)
    np.testing.assert_allclose(p2.image[y, x] / 255.0, expected, atol=0.03)


def test_expression_moves_landmarks_with_the_field():
    ident = FaceIdentity.random(np.random.default_rng(2))
    e = Expression(smile=0.7, open=0.5, brow=0.4)
    f = make_face(ident, e)
    lm = face_landmarks_normalised(ident)
    dX, dY, dh = expression_field(ident, e, lm[:, 0], lm[:, 1])
    np.testing.assert_allclose(f.landmarks3d[:, 0], (lm[:, 0] + dX) * 80 + 97)
    np.testing.assert_allclose(f.landmarks3d[:, 1], (lm[:, 1] + dY) * 80 + 112)
    neutral = make_face(ident)
    motion = np.linalg.norm(f.landmarks3d[:, :2] - neutral.landmarks3d[:, :2], axis=1)
    assert motion[[48, 54]].min() > 2.0  # smile moves the corners
    assert motion[57] > 5.0  # the jaw drops
    assert f.landmarks3d[48, 1] < neutral.landmarks3d[48, 1]  # corners go up
    assert f.landmarks3d[19, 1] < neutral.landmarks3d[19, 1]  # brows go up
    # the frontal view of the deformed face shows the deformed mesh
    assert f.mask.sum() > 0.9 * neutral.mask.sum()
    assert np.abs(f.depth - neutral.depth)[f.mask & neutral.mask].max() > 1.0


@pytest.mark.parametrize("seed", [1, 2])
def test_blink_closes_the_identity_eye_and_open_minus_one_closes_lips(seed):
    ident = FaceIdentity.random(np.random.default_rng(seed))
    f = make_face(ident, Expression(blink=1.0, open=-1.0))
    lm = f.landmarks3d
    open_eyes = make_face(ident).landmarks3d
    # the upper lid lands on the (unmoved) lower lid curve, the lower inner lip on the upper one
    for moving, curve in (([37, 38], [36, 41, 40, 39]), ([43, 44], [42, 47, 46, 45]),
                          ([65, 66, 67], [60, 61, 62, 63, 64])):
        target = np.interp(lm[moving, 0], open_eyes[curve, 0], open_eyes[curve, 1])
        np.testing.assert_allclose(lm[moving, 1], target, atol=1e-6)
    np.testing.assert_allclose(lm[[36, 39, 40, 41, 61, 62, 63]], open_eyes[[36, 39, 40, 41, 61, 62, 63]])
    assert (open_eyes[[41, 40]] - open_eyes[[37, 38]])[:, 1].min() > 3.0


def test_expression_field_has_no_fold():
    ident = FaceIdentity.random(np.random.default_rng(4))
    f = make_face(ident, Expression(smile=1.0, open=1.0, brow=1.0, blink=1.0))
    v = f.verts
    m = f.vert_mask[:-1, :-1] & f.vert_mask[1:, :-1] & f.vert_mask[:-1, 1:]
    du = v[:-1, 1:, :2] - v[:-1, :-1, :2]
    dv = v[1:, :-1, :2] - v[:-1, :-1, :2]
    jac = du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]
    assert jac[m].min() > -1e-9


def test_determinism_under_a_seed():
    a = make_collection(2, seed=7, image_size=(120, 120), face_px=70)
    b = make_collection(2, seed=7, image_size=(120, 120), face_px=70)
    c = make_collection(2, seed=8, image_size=(120, 120), face_px=70)
    for pa, pb in zip(a, b):
        assert isinstance(pa, SyntheticPhoto)
        np.testing.assert_array_equal(pa.image, pb.image)
        np.testing.assert_array_equal(pa.landmarks, pb.landmarks)
        assert pa.identity == pb.identity and pa.expression == pb.expression
    assert not np.array_equal(a[0].image, c[0].image)
    p = a[0]
    assert p.image.shape == (120, 120, 3) and p.image.dtype == np.uint8
    assert p.landmarks.shape == (68, 2) and p.visible.shape == (68,) and p.visible.dtype == bool
    assert p.rvec.shape == (3,) and p.tvec.shape == (3,) and p.camera.shape == (3, 3)


def test_driver_video_is_smooth():
    frames = make_driver_video(12, seed=3, image_size=(128, 128), face_px=70, supersample=1)
    assert len({f.identity for f in frames}) == 1 and len({f.light for f in frames}) == 1
    e = np.array([f.expression.as_array() for f in frames])
    assert np.abs(np.diff(e, axis=0)).max() < 0.25
    lm = np.array([f.landmarks for f in frames])
    assert np.abs(np.diff(lm, axis=0)).max() < 5.0


def test_bad_parameters():
    with pytest.raises(ValueError):
        Expression(blink=1.5)
    f = make_face()
    rvec, tvec, K = look_at_pose(0, 0, 0, face_px=100, image_size=(100, 100))
    with pytest.raises(ValueError):
        render_photo(f, rvec=rvec, tvec=np.array([0.0, 0.0, -500.0]), camera=K, image_size=(100, 100))
    with pytest.raises(ValueError):
        render_photo(f, rvec=rvec, tvec=tvec, camera=K, image_size=(100, 100), noise_sigma=0.1)


def test_dlib_finds_synthetic_faces():
    dlib = pytest.importorskip("dlib")
    frm = pytest.importorskip("face_recognition_models")
    detector = dlib.get_frontal_face_detector()
    predictor = dlib.shape_predictor(frm.pose_predictor_model_location())
    photos = make_collection(10, seed=11, face_px=130, yaw_range=15, pitch_range=8)
    found, errors = 0, []
    for p in photos:
        rects = detector(p.image, 1)
        if not rects:
            continue
        found += 1
        shape = predictor(p.image, max(rects, key=lambda r: r.area()))
        lm = np.array([[q.x, q.y] for q in shape.parts()], float)
        iod = np.linalg.norm(p.landmarks[36:42].mean(0) - p.landmarks[42:48].mean(0))
        errors.append(np.linalg.norm(lm[17:] - p.landmarks[17:], axis=1).mean() / iod)
    assert found >= 8
    assert np.mean(errors) < 0.12
