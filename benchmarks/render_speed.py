"""Speed of the render backends per frame (one core): the 3D ``mesh3d`` and, for reference, ``tps2d``.

    .venv/bin/python benchmarks/render_speed.py [--size 512] [--face-px 250] [--repeats 30]

A synthetic puppet (the ground-truth face of an identity with an expression: its parametrised
mesh and albedo) is rendered into a --size x --size frame with the face --face-px wide, at a few
head poses, with the default params (feather 3, coverage from a collection-like fall-off at the
face rim). The tps2d backend renders the same texture to the same pose and target fiducials.
Also timed: visibility alone by open3d ray casting (scene build and one ray per pixel of the face
box, one thread), the method the z-buffer replaces. The issue asks for <= 30 ms per frame.

Each figure is the median over --repeats renders of each pose (after one warm-up render, which
includes numba's compilation on the first run).
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from persona.plugins.builtin.render import Tps2dRender  # noqa: E402
from persona.plugins.builtin.render3d import RaycastRender  # noqa: E402
from persona.plugins.face.mesh import grid_triangles  # noqa: E402
from persona.plugins.face.synthetic import Expression, look_at_pose, make_face  # noqa: E402
from persona.plugins.kinds import Pose, Puppet  # noqa: E402

POSES = ((0.0, 0.0, 0.0), (25.0, 8.0, 4.0), (-20.0, -10.0, -3.0))  # yaw, pitch, roll (degrees)


def puppet() -> Puppet:
    """A synthetic puppet frame: mesh, texture 0-255, coverage falling off over the rim of the face."""
    face = make_face(expression=Expression(smile=0.6, open=0.4))
    mesh = np.where(face.vert_mask[..., None], face.verts, np.nan).astype(np.float32)
    inside = cv2.distanceTransform(face.vert_mask.astype(np.uint8), cv2.DIST_L2, 5)
    coverage = np.clip(inside / 10.0, 0, 1).astype(np.float32)
    return Puppet(appearance=(face.vert_albedo * 255).astype(np.float32), coverage=coverage,
                  fiducials=face.fiducials3d[:, :2].astype(np.float64), mesh=mesh)


def timed(fn, repeats: int) -> float:
    """Median wall time of fn() in ms after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def open3d_visibility(p: Puppet, pose: Pose, size: int) -> float:
    """Ray-cast the posed mesh with open3d (one thread) through every pixel of its box: hit fraction."""
    import open3d as o3d

    finite = np.isfinite(p.mesh).all(axis=2)
    rotation = cv2.Rodrigues(pose.rvec)[0]
    cam = np.where(finite[..., None], p.mesh, 0).reshape(-1, 3) @ rotation.T + pose.tvec
    scene = o3d.t.geometry.RaycastingScene(nthreads=1)
    scene.add_triangles(o3d.core.Tensor(cam.astype(np.float32)), o3d.core.Tensor(grid_triangles(finite)))
    xy = cam[finite.ravel()] @ pose.camera.T
    xy = xy[:, :2] / xy[:, 2:]
    x0, y0 = np.maximum(np.floor(xy.min(axis=0)).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(xy.max(axis=0)).astype(int) + 1, size)
    ys, xs = np.mgrid[y0:y1, x0:x1]
    rays = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1) @ np.linalg.inv(pose.camera).T
    t_hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(rays), rays], 1).astype(np.float32)))
    return float(np.isfinite(t_hit["t_hit"].numpy()).mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=512, help="frame height and width")
    parser.add_argument("--face-px", type=float, default=250.0, help="width of the face oval in the frame")
    parser.add_argument("--repeats", type=int, default=30, help="timed renders per pose")
    args = parser.parse_args()

    p = puppet()
    frame = np.random.default_rng(0).integers(0, 256, (args.size, args.size, 3), dtype=np.uint8)
    backends = {"mesh3d": RaycastRender(), "tps2d": Tps2dRender()}
    rows = {name: [] for name in (*backends, "open3d visibility only")}
    for yaw, pitch, roll in POSES:
        rvec, tvec, camera = look_at_pose(yaw, pitch, roll, face_px=args.face_px, image_size=(args.size,) * 2)
        pose = Pose(rvec, tvec, camera, 0.0)
        for name, backend in backends.items():
            rows[name].append(timed(lambda b=backend, q=pose: b.render(p, p.fiducials, q, frame), args.repeats))
        rows["open3d visibility only"].append(timed(lambda q=pose: open3d_visibility(p, q, args.size), args.repeats))
        face = backends["mesh3d"].render(p, p.fiducials, pose, frame).mask > 0.5
        cols = np.nonzero(face.any(axis=0))[0]
        print(f"pose yaw {yaw:+.0f} pitch {pitch:+.0f} roll {roll:+.0f}: face {cols[-1] - cols[0] + 1} px wide, "
              f"{face.sum()} face pixels")
    print(f"\n{args.size}x{args.size} frame, one core, median of {args.repeats} renders per pose (ms/frame):")
    for name, ms in rows.items():
        print(f"  {name:24s} " + "  ".join(f"{m:6.1f}" for m in ms) + f"   (median {np.median(ms):.1f})")
    print("target for mesh3d: <= 30 ms/frame")


if __name__ == "__main__":
    main()
