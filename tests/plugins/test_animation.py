"""plugins/animation.py: the face in the files' frame and the head's pose as a node's rotation and translation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from persona.plugins.animation import FLIP, face_mesh, head_motion, to_file_frame


def _face(h=60, w=50):
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    depth = 100 + 0.02 * ((xx - w / 2) ** 2 + (yy - h / 2) ** 2)  # a dome: its middle nearest the camera
    mask = (xx - w / 2) ** 2 / (w / 2.2) ** 2 + (yy - h / 2) ** 2 / (h / 2.2) ** 2 < 1
    return depth, mask


def test_the_face_is_in_metres_facing_the_viewer_with_its_eyes_63_mm_apart():
    depth, mask = _face()
    fiducials = np.zeros((49, 2))
    fiducials[19:25] = [15, 25]  # the left eye's points, then the right's: 20 px apart
    fiducials[25:31] = [35, 25]
    mesh = face_mesh(depth, mask, fiducials, np.zeros(depth.shape + (3,), np.uint8))
    left, right = to_file_frame(np.array([[15, 25, 0], [35, 25, 0]]), mesh.origin, mesh.scale)
    assert np.linalg.norm(right - left) == pytest.approx(0.063, rel=1e-6) and right[0] > left[0]
    assert 0.8 * mask.sum() < len(mesh.vertices) <= mask.sum()  # the mask's points in a quad of the grid
    middle = np.argmin(np.abs(mesh.rows - 30) + np.abs(mesh.cols - 25))
    assert (mesh.normals[:, 2] > 0).all() and mesh.normals[middle, 2] > 0.99  # a dome facing the viewer, +z
    assert mesh.vertices[middle, 2] == mesh.vertices[:, 2].max()  # its middle nearest the viewer
    assert mesh.vertices[np.argmin(mesh.rows), 1] > mesh.vertices[np.argmax(mesh.rows), 1]  # the top row is up
    assert 0 < mesh.uvs.min() and mesh.uvs.max() < 1
    half = face_mesh(depth, mask, fiducials, step=2)
    assert len(half.vertices) < len(mesh.vertices) / 3 and (half.rows % 2 == 0).all()


def test_the_head_node_moves_the_face_where_the_camera_sees_it():
    """For every frame, rotation and translation of the node applied to a vertex give the point the
    pose puts in front of the camera (in the files' frame, less the mean path)."""
    rng = np.random.default_rng(0)
    poses = np.zeros((5, 10))
    poses[:, :3] = rng.normal(0, 0.3, (5, 3))
    poses[:, 3:6] = rng.normal(0, 20, (5, 3)) + [0, 0, 900]
    poses[2, :6] = np.nan  # a frame without a pose takes its neighbour's
    origin, scale = np.array([97.0, 110.0, 40.0]), 0.001
    quats, moves = head_motion(poses, origin, scale)
    assert np.allclose(np.linalg.norm(quats, axis=1), 1) and np.allclose(moves.mean(axis=0), 0, atol=1e-6)
    filled = poses.copy()
    filled[2] = poses[1]
    points = rng.normal(100, 30, (7, 3))
    seen = []
    for t in range(5):
        rotation = Rotation.from_rotvec(filled[t, :3]).as_matrix()
        seen.append(scale * (points @ rotation.T + filled[t, 3:6]) @ FLIP)
    path = np.mean([scale * (rotation_of(filled[t]) @ origin + filled[t, 3:6]) @ FLIP for t in range(5)], axis=0)
    vertices = to_file_frame(points, origin, scale)
    for t in range(5):
        placed = Rotation.from_quat(quats[t]).apply(vertices) + moves[t]
        np.testing.assert_allclose(placed, seen[t] - path, atol=1e-5)
    assert all(np.dot(quats[t], quats[t - 1]) >= 0 for t in range(1, 5))  # the short way between frames


def rotation_of(pose):
    return Rotation.from_rotvec(pose[:3]).as_matrix()


def test_a_drive_without_any_pose_rests():
    quats, moves = head_motion(np.full((3, 10), np.nan), np.zeros(3), 1.0)
    assert np.allclose(quats, [0, 0, 0, 1]) and np.allclose(moves, 0)
