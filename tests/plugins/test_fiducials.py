"""Collection statistics of pose-corrected fiducials: NaN points and a diverged photo."""

import numpy as np

from persona.plugins.face.blend import expression_weights
from persona.plugins.face.fiducials import mean_shape, median_shape, shape_distance
from persona.plugins.face.template import generic_template
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
