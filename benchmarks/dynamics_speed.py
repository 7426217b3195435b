"""The driver's per-frame 3D flow (plugins/face/dynamics.py): milliseconds per frame on one core,
and the accuracy of the meshes on a synthetic driver video.

    .venv/bin/python benchmarks/dynamics_speed.py [--frames 24] [--runs 3] [--flow dis]

The video is ``make_driver_video`` (256x256 px, face 140 px wide, smooth expressions and head
motion, fixed light); its GT meshes are ``make_face(identity, e_t).verts``. The driver's average
is its neutral face (depth, grey albedo, rank-4 basis of its Lambertian images), which isolates the
per-frame steps from photometric stereo (ALGORITHMS §9.4).

Timing: ``track_frame`` (frontalise, visibility, reference, flow, shading refinement) over every
frame, after one warm-up frame, median over --runs passes of the wall and the CPU time (the CPU time
is the steadier figure on a shared machine), one thread everywhere (BLAS, OpenMP, OpenCV); then ``smooth_tracks`` + ``frame_mesh`` per frame. Budget: the whole per-frame drive
(dynamics + transfer + texture + render) must reach 5 fps on 2 cores, i.e. dynamics ≤ ~150 ms
per frame on one core.

Accuracy: RMS 3D distance (canonical px) of M_D^t to the GT mesh over the face, with the GT pose,
and with PnP poses from noisy landmarks (σ = --landmark-noise px, nose and eye corners, smoothed), raw and after a
rigid fit to the truth.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

LUMA = np.array([0.299, 0.587, 0.114])
RIGID = list(range(27, 36)) + [36, 39, 42, 45]  # nose and eye corners: what expressions move least


def ground_truth_model(identity):
    from persona.plugins.face import dynamics as dy
    from persona.plugins.face.synthetic import make_face

    face = make_face(identity)
    rows = np.stack([face.albedo] + [face.albedo * face.normals[..., k:k + 1] for k in range(3)])
    rows = rows.reshape(4, -1) * np.repeat(face.mask.ravel(), 3)
    basis = np.linalg.qr(rows.T)[0].T.reshape(4, *face.albedo.shape)
    return dy.DriverModel.build(face.depth, face.albedo @ LUMA, face.mask, basis), face


def rigidly_aligned_error(mesh, truth, mask):
    a, b = mesh[mask].astype(np.float64), truth[mask].astype(np.float64)
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(u @ vt))
    rotation = (u @ np.diag([1, 1, d]) @ vt).T
    return float(np.sqrt(np.mean(np.sum(((a - ca) @ rotation.T + cb - b) ** 2, axis=1))))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--flow", default="dis", help="flow backend name (default: the registry's default, dis)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--landmark-noise", type=float, default=0.5, help="σ in px of the landmarks given to PnP")
    args = ap.parse_args()

    from persona.plugins.builtin.pose import solve_pose
    from persona.plugins.face import dynamics as dy
    from persona.plugins.face.synthetic import make_driver_video, make_face
    from persona.plugins.kinds import Pose
    from persona.plugins.manager import default_registry

    flow = default_registry().get("flow", args.flow)()
    t0 = time.perf_counter()
    frames = make_driver_video(args.frames, seed=args.seed)
    identity = frames[0].identity
    truths = [make_face(identity, f.expression).verts for f in frames]
    model, neutral = ground_truth_model(identity)
    mask = model.mask & neutral.vert_mask
    poses = [Pose(f.rvec, f.tvec, f.camera, 0.0) for f in frames]
    images = [f.image for f in frames]
    print(f"{args.frames} frames of a synthetic driver video (seed {args.seed}, 256x256, rendered in "
          f"{time.perf_counter() - t0:.0f} s); canonical grid {model.shape[1]}x{model.shape[0]}; flow '{args.flow}'; "
          f"one thread")

    configs = {"flow only": dy.DynamicsParams(shading_refinement=False), "flow + shading": dy.DynamicsParams()}
    print("\nms per frame (median of runs):")
    for label, params in configs.items():
        dy.track_frame(model, images[0], poses[0], flow, params)  # warm-up: operators, scene, numba
        times, cpu = [], []
        for _ in range(args.runs):
            start, start_cpu = time.perf_counter(), time.process_time()
            tracks = [dy.track_frame(model, im, p, flow, params) for im, p in zip(images, poses)]
            times.append(1000 * (time.perf_counter() - start) / len(images))
            cpu.append(1000 * (time.process_time() - start_cpu) / len(images))
        start = time.perf_counter()
        smoothed = dy.smooth_tracks(tracks, params)
        meshes = [dy.frame_mesh(model, t, p) for t, p in zip(smoothed, poses)]
        dy.mean_mesh(meshes)
        finish = 1000 * (time.perf_counter() - start) / len(images)
        print(f"  {label:<15} track_frame {statistics.median(times):6.1f} ms wall, {statistics.median(cpu):6.1f} ms "
              f"CPU ({args.runs} runs, wall: {', '.join(f'{t:.1f}' for t in times)}); smooth + mesh + mean "
              f"{finish:.1f} ms")

    print("\nRMS 3D error of M_D^t vs GT (canonical px, mean over frames), GT pose and GT average:")
    base = np.mean([dy.mesh_error(model.rest_mesh, g, mask) for g in truths])
    print(f"  no motion (M_D^t = average)      {base:.3f}")
    for label, params in configs.items():
        for smooth in (0.0, params.time_sigma):
            p = params.model_copy(update={"time_sigma": smooth})
            meshes, _ = dy.driver_meshes(model, images, poses, flow, p, pose_sigma=0)
            err = np.mean([dy.mesh_error(m, g, mask) for m, g in zip(meshes, truths)])
            when = f"time σ {smooth:g}" if smooth else "no time smoothing"
            print(f"  {label:<15} {when:<18} {err:.3f}  ({err / base:.2f}x no motion)")

    rng = np.random.default_rng(5)
    points = neutral.landmarks3d[RIGID].copy()
    points[:, 2] = [model.depth[int(round(y)), int(round(x))] for x, y in points[:, :2]]
    estimated = []
    for f in frames:
        seen = f.landmarks[RIGID] + rng.normal(0, args.landmark_noise, (len(RIGID), 2))
        rvec, tvec = solve_pose(points, seen, f.camera)
        estimated.append(Pose(rvec, tvec, f.camera, 0.0))
    print(f"\nwith PnP poses (landmarks + noise σ {args.landmark_noise:g} px, smoothed σ 1.5 frames), GT average:")
    base_rigid = np.mean([rigidly_aligned_error(model.rest_mesh, g, mask) for g in truths])
    for label, params in configs.items():
        meshes, _ = dy.driver_meshes(model, images, estimated, flow, params, pose_sigma=1.5)
        raw = np.mean([dy.mesh_error(m, g, mask) for m, g in zip(meshes, truths)])
        fitted = np.mean([rigidly_aligned_error(m, g, mask) for m, g in zip(meshes, truths)])
        print(f"  {label:<15} raw {raw:.3f} (no motion {base:.3f}); after a rigid fit {fitted:.3f} "
              f"(no motion {base_rigid:.3f})")


if __name__ == "__main__":
    main()
