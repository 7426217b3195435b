"""dlib's landmarks (persona.plugins.builtin.landmarks) on frames of an HD clip: a large face is found
on the frame reduced to ``detect_side``, a small one at full size, and the 68 points are fitted at
full size either way (../shared/data; skipped when absent)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from persona.plugins.builtin.landmarks import DlibLandmarks, dlib_models, skipped_levels
from persona.stores import media

pytestmark = pytest.mark.realdata


def _hd_frame(shared_data, face_scale: float) -> np.ndarray:
    """A 1920 x 1080 frame holding a frame of woman_expressions.mp4 (512², her face about 320 px)
    resized by ``face_scale``, on her own background colour."""
    with media.VideoReader(shared_data / "videos" / "woman_expressions.mp4") as reader:
        frame = next(f for i, f in reader.frames() if i == 60)
    small = cv2.resize(frame, None, fx=face_scale, fy=face_scale, interpolation=cv2.INTER_AREA if face_scale < 1
                       else cv2.INTER_CUBIC)
    canvas = np.empty((1080, 1920, 3), np.uint8)
    canvas[:] = frame[5, 5]
    canvas[20:20 + small.shape[0], 700:700 + small.shape[1]] = small
    return canvas


def test_an_hd_frame_is_searched_small_first_and_fitted_at_full_size(shared_data):
    """Her face at 2x (about 640 px): found on the frame reduced to 800 px, and its 68 points lie
    within 1 % of the inter-ocular distance (median) of those found on the full frame. At 0.25x
    (about 80 px, 35 px once reduced) the reduced search finds nothing, and the full-size one does."""
    large, tiny = _hd_frame(shared_data, 2.0), _hd_frame(shared_data, 0.25)
    fast, full = DlibLandmarks({"detect_side": 800}), DlibLandmarks({"detect_side": None})
    assert fast.attempts(large.shape[:2])[0][0] == pytest.approx(800 / 1920)
    assert full.attempts(large.shape[:2])[0][0] == 1
    a, b = fast.detect(large).points, full.detect(large).points
    iod = np.linalg.norm(b[36:42].mean(0) - b[42:48].mean(0))
    print(f"\nIOD {iod:.0f} px, median difference {np.median(np.linalg.norm(a - b, axis=1)) / iod:.4f} IOD")
    assert not np.allclose(a, b)  # the reduced search found it, and placed the fit a little differently
    assert iod > 150 and np.median(np.linalg.norm(a - b, axis=1)) < 0.01 * iod
    reduced = cv2.resize(tiny, None, fx=800 / 1920, fy=800 / 1920, interpolation=cv2.INTER_AREA)
    assert len(dlib_models()[0].run(reduced, 0, 0.0)[0]) == 0  # too small to be found there
    c, d = fast.detect(tiny).points, full.detect(tiny).points
    np.testing.assert_allclose(c, d)  # the same full-size search found it


@pytest.mark.parametrize("clip", ["woman_gaze_fringe.mp4", "man_frontal_480.mp4", "woman_expressions.mp4",
                                  "man_glasses_phone_720p.mp4"])
def test_a_face_of_known_height_is_found_from_coarser_levels_with_the_same_box(shared_data, clip):
    """Told how tall the face is, dlib's search starts several pyramid levels down and finds the same box
    and the same 68 points as the whole search, to the bit, on every 10th of a clip's first 60 frames (her
    face at 512², his at 480² and 720p). Told a face four times as tall as it is, it still finds it (the
    coarser search finds nothing, and the whole one runs)."""
    detector = DlibLandmarks()
    with media.VideoReader(shared_data / "videos" / clip) as reader:
        frames = [f for i, f in reader.frames() if i % 10 == 0 and i < 60]
    for frame in frames:
        whole = detector.detect(frame)
        height = 1.3 * (whole.points[:, 1].max() - whole.points[:, 1].min())  # about the face oval's
        scale = detector.attempts(frame.shape[:2])[0][0]  # the 720p frame is searched at 800 px
        assert skipped_levels(height * scale) >= 3  # of the 8-10 levels a whole search scans
        known = detector.detect(frame, face_height=height)
        np.testing.assert_array_equal(known.box, whole.box)
        np.testing.assert_array_equal(known.points, whole.points)
    tiny = cv2.resize(frames[0], None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(detector.detect(tiny, face_height=2 * height).points, detector.detect(tiny).points)
