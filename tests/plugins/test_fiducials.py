"""Collection statistics of pose-corrected fiducials: NaN points and a diverged photo."""

import numpy as np

from persona.plugins.face.blend import expression_weights
from persona.plugins.face.fiducials import mean_shape, median_shape, rest_shape, shape_distance, similarity_residual
from persona.plugins.face.template import IDX49, generic_template
from persona.plugins.face.tracks import bridge
from persona.plugins.face.warp import tps_map


def collection(n=40, seed=0):
    """n photos' fiducials: the template's, each moved by a random expression of a few px."""
    rng = np.random.default_rng(seed)
    return generic_template().fiducials3d[:, :2] + rng.normal(0, 2.0, (n, 49, 2))


def test_a_diverged_photo_moves_neither_the_median_nor_the_screened_mean():
    clean = collection()
    diverged = clean[0].copy()
    diverged[14] = [75145.0, 13438.0]  # the nose point, pose-corrected into another galaxy
    diverged[15:18] += [-300.0, 40.0]
    photos = np.concatenate([clean, diverged[None]])
    median = median_shape(photos)
    assert np.abs(median - median_shape(clean)).max() < 0.5
    distance = shape_distance(photos, median)
    tolerance = 16.0  # the screen's default max_distance
    assert distance[:-1].max() < 5 and distance[-1] > tolerance
    kept = photos[distance <= tolerance]
    np.testing.assert_allclose(mean_shape(kept), clean.mean(axis=0), atol=1e-9)
    assert np.abs(photos.mean(axis=0) - clean.mean(axis=0)).max() > 1000  # what a plain mean did


def test_nan_points_are_left_out_point_by_point():
    photos = collection()
    truth = photos.mean(axis=0)
    turned = photos.copy()
    turned[:10, 14:18] = np.nan  # ten turned photos do not see the far side of the nose
    mean = mean_shape(turned)
    np.testing.assert_allclose(mean[:14], truth[:14])
    np.testing.assert_allclose(mean[14:18], photos[10:, 14:18].mean(axis=0))
    assert np.isfinite(shape_distance(turned, median_shape(turned))).all()
    nobody = turned.copy()
    nobody[:, 20] = np.nan
    np.testing.assert_array_equal(mean_shape(nobody)[20], generic_template().fiducials3d[20, :2])


def test_expression_weights_compare_a_turned_photo_on_its_visible_half():
    photos = collection(3)
    target = photos[0].copy()
    turned = photos.copy()
    turned[0, 30:] = np.nan
    e = expression_weights(turned, target, sigma=10.0)
    assert e[0] == 1.0  # the visible half matches exactly
    np.testing.assert_allclose(e[1:], expression_weights(photos[1:], target, sigma=10.0))
    assert np.isfinite(expression_weights(photos, np.where(np.arange(49)[:, None] < 5, np.nan, target), 10.0)).all()


def test_tps_and_bridge_leave_out_points_not_visible():
    source = collection(2)
    target = generic_template().fiducials3d[:, :2]
    holes = source[0].copy()
    holes[40:] = np.nan
    warp = tps_map(target[:40], source[0, :40], (244, 194), step=4)
    np.testing.assert_allclose(tps_map(target, holes, (244, 194), step=4), warp)
    track = np.stack([source[0], source[1], source[1]])
    track[1, 5] = np.nan
    bridged = bridge(track, np.array([True, True, True]))
    np.testing.assert_allclose(bridged[1, 5], (track[0, 5] + track[2, 5]) / 2)


def _turned(shape: np.ndarray, degrees: float, scale: float, shift) -> np.ndarray:
    a = np.radians(degrees)
    rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return scale * (shape - shape.mean(axis=0)) @ rotation.T + shape.mean(axis=0) + np.asarray(shift)


def test_a_similarity_takes_out_scale_rotation_and_shift_and_nothing_else():
    face = generic_template().fiducials3d[:, :2]
    assert similarity_residual(_turned(face, 8.0, 1.2, (5, -3)), face) < 1e-9
    gaping = face.copy()
    gaping[[IDX49.index(i) for i in (56, 57, 58, 65, 66, 67)], 1] += 10  # the lower lip 10 px down
    assert 1.0 < similarity_residual(_turned(gaping, 8.0, 1.2, (5, -3)), face) < 10 * np.sqrt(6 / 49)


def test_the_rest_shape_of_a_collection_that_mostly_gapes_and_frowns_is_its_resting_face():
    """A person's 40 photos: 12 at rest (their own proportions, not the template's), 16 with the mouth
    wide open, 12 frowning (brows down, lids narrowed), each turned, scaled and moved a little in the frame
    and jittered by 0.5 px. Their mean gapes half open, 2 px (RMS) from the mean of the 12 at rest; the rest
    shape of the quarter nearest the generic face is within 0.5 px of it, and share 1 is the mean itself."""
    rng = np.random.default_rng(3)
    rest = generic_template().fiducials3d[:, :2] * np.array([1.06, 0.96])  # a wider, shorter face than the template
    lower_lip = [IDX49.index(i) for i in (56, 57, 58, 65, 66, 67)]
    brows, upper_lids = [IDX49.index(i) for i in range(17, 27)], [IDX49.index(i) for i in (37, 38, 43, 44)]
    photos = []
    for kind in ["rest"] * 12 + ["gape"] * 16 + ["frown"] * 12:
        face = rest.copy()
        if kind == "gape":
            face[lower_lip, 1] += rng.uniform(10, 18)
        if kind == "frown":
            face[brows, 1] += 6
            face[upper_lids, 1] += 3
        face = _turned(face, rng.uniform(-3, 3), rng.uniform(0.97, 1.03), rng.uniform(-2, 2, 2))
        photos.append(face + rng.normal(0, 0.5, face.shape))
    photos = np.stack(photos)
    rms = lambda a, b: float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))  # noqa: E731
    at_rest = mean_shape(photos[:12])  # the best any choice of photos can do
    assert rms(at_rest, rest) < 0.8
    assert rms(mean_shape(photos), at_rest) > 2.0
    assert rms(rest_shape(photos, 0.25), at_rest) < 0.5
    np.testing.assert_array_equal(rest_shape(photos, 1.0), mean_shape(photos))
