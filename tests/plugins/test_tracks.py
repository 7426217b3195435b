"""Steadying a detector's landmarks with the frames' own motion (plugins/face/tracks.py)."""

import cv2
import numpy as np

from persona.plugins.face.tracks import steadied


def _moving_texture(n: int, path: np.ndarray) -> np.ndarray:
    """n frames (n, 120, 160, 3) of one smooth random texture, frame t shifted by path[t] (px)."""
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (200, 240)).astype(np.float32), (0, 0), 2.0)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX)
    frames = []
    for dx, dy in path:
        m = np.float32([[1, 0, dx], [0, 1, dy]])
        grey = cv2.warpAffine(base, m, (240, 200), flags=cv2.INTER_CUBIC)[40:160, 40:200]
        frames.append(np.repeat(grey[..., None], 3, axis=-1).astype(np.uint8))
    return np.stack(frames)


def test_steadying_averages_the_detectors_noise_but_keeps_the_motion():
    """Points on a texture that moves 0-4 px a frame (a fast onset, then back) at known places: with
    0.3 px of detector noise per coordinate, the points steadied over 2 frames each side are nearer
    the truth (error under 0.7 of the noisy points'); exact points stay within 0.05 px of where they
    are, however fast the texture moves, so the motion is not smoothed away (no lag at an onset)."""
    n = 24
    t = np.arange(n)
    path = np.stack([12 * np.exp(-((t - 12) / 3.0) ** 2), 0.5 * t], axis=-1)  # up to 4 px a frame in x
    frames = _moving_texture(n, path)
    grid = np.stack(np.meshgrid(np.linspace(40, 120, 5), np.linspace(30, 90, 4)), axis=-1).reshape(-1, 2)
    truth = grid[None] + path[:, None]
    found = np.ones(n, bool)
    np.testing.assert_allclose(steadied(truth, frames, found, 2), truth, atol=0.05)
    noisy = truth + np.random.default_rng(0).normal(0, 0.3, truth.shape)
    before = np.sqrt(np.mean((noisy - truth) ** 2))
    after = np.sqrt(np.mean((steadied(noisy, frames, found, 2) - truth) ** 2))
    assert after < 0.7 * before, (before, after)


def test_frames_without_a_face_neither_change_nor_lend():
    """A frame not found keeps its points (whatever they are), and its neighbours take nothing from it;
    radius 0 is the detector's points as they are."""
    n = 6
    path = np.stack([np.arange(n) * 0.5, np.zeros(n)], axis=-1)
    frames = _moving_texture(n, path)
    points = np.array([[60.0, 50.0], [100.0, 70.0]])[None] + path[:, None]
    points[3] = 0.0  # garbage where no face was found
    found = np.ones(n, bool)
    found[3] = False
    out = steadied(points, frames, found, 2)
    np.testing.assert_array_equal(out[3], points[3])
    np.testing.assert_allclose(out[found], points[found], atol=0.05)
    np.testing.assert_array_equal(steadied(points, frames, found, 0), points)


def test_a_change_the_flow_cannot_see_is_kept():
    """A point that steps 3 px at frame 6 on a texture that holds still (a lid that shuts: the
    detector sees it, the flow between the frames does not) keeps its step to within 0.1 px: the
    neighbours' carried points land 3 px from its own and lend next to nothing (AGREE)."""
    n = 12
    frames = _moving_texture(n, np.zeros((n, 2)))
    points = np.tile(np.array([[70.0, 50.0], [110.0, 60.0]]), (n, 1, 1))
    points[6:, 0, 1] += 3.0
    np.testing.assert_allclose(steadied(points, frames, np.ones(n, bool), 2), points, atol=0.1)
