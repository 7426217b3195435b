"""How much of the head's real motion the smoothing of the driver's pose takes away, and which
``stages.motion.params.pose_sigma`` would place the face best.

On a finished 3D run's store, for every drive of the workflow: each frame's misplacement of B's face
in ``composite.mp4`` against A's frame (the mean of a dense flow, DIS, from A's frame to the composite
inside the rendered face's mask), set against the difference between A's per-frame pose and the
smoothed one the drive used (both projected at the centre of B's mesh). A negative slope means the
smoothing removed real motion: the face lags where the head went. Then, taking the misplacement as
the error of the drive's smoothed pose, the error each ``pose_sigma`` would have left (rms, frame px,
a constant offset removed: B's face is not A's). docs/expression.md, "The head's pose, smoothed less".

    python benchmarks/pose_smoothing.py workflows/obama_self_reenactment.yaml
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from persona.dag.workflow import load_workflow
from persona.plugins.builtin.render3d import project
from persona.plugins.face.dynamics import smooth_in_time
from persona.plugins.kinds import Pose
from persona.stores.layout import Collection, open_store

SIGMAS = (0.0, 0.5, 0.75, 1.0, 1.5, 2.0)


def misplacement(drive: Collection, frames: Collection) -> np.ndarray:
    """(T, 2) mean flow from A's frame to the composite inside the face's mask (NaN without a face)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    out = np.full((drive.n, 2), np.nan)
    for start, stop in drive.shard_ranges():
        composites, masks = drive.array("composite/rgb")[start:stop], drive.array("render/mask")[start:stop]
        originals = frames.array("photos/rgb")[start:stop]
        for j, (composite, mask, original) in enumerate(zip(composites, masks, originals)):
            face = mask > 127
            if face.any():
                h, w = face.shape
                grey = [cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) for image in (original[:h, :w], composite)]
                out[start + j] = dis.calc(*grey, None)[face].mean(axis=0)
    return out


def centres(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(T, 2) where each pose puts the centre of ``points`` (n, 3) in the frame."""
    return np.array([project(points, Pose.from_vector(p))[0].mean(axis=0) if np.isfinite(p).all()
                     else (np.nan, np.nan) for p in poses])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("workflow")
    args = parser.parse_args()
    wf = load_workflow(args.workflow)
    root = open_store(wf.store, mode="r")
    for plan in wf.drive_plans():
        drive, frames = Collection(root, plan.cast.drive), Collection(root, plan.cast.frames)
        mesh = root[f"{plan.cast.drive}/mesh"][0]
        points = mesh[np.isfinite(mesh).all(axis=2)][::50]
        used, raw = drive.array("pose")[:], frames.array("pose")[:]
        shift = misplacement(drive, frames)
        placed = centres(used, points)
        lost = centres(raw, points) - placed  # A's per-frame pose against the smoothed one
        ok = np.isfinite(shift).all(axis=1) & np.isfinite(lost).all(axis=1)
        print(f"{plan.name}: {ok.sum()} frames, misplacement rms {np.sqrt((shift[ok] ** 2).sum(1).mean()):.3f} px, "
              f"per-frame minus smoothed pose rms {np.sqrt((lost[ok] ** 2).sum(1).mean()):.3f} px")
        for axis, name in enumerate("xy"):
            slope = np.polyfit(lost[ok, axis], shift[ok, axis], 1)[0]
            r = np.corrcoef(lost[ok, axis], shift[ok, axis])[0, 1]
            print(f"  {name}: misplacement on (per-frame - smoothed): slope {slope:+.2f}, r {r:+.2f}")
        truth = placed - shift  # where the face should have been
        found = np.isfinite(raw).all(axis=1)
        for sigma in SIGMAS:
            poses = np.where(found[:, None], raw, used)  # frames without a face: the drive's bridged pose
            if sigma > 0:
                poses[:, :6] = smooth_in_time(poses[:, :6], sigma)
            error = centres(poses, points) - truth
            error -= np.median(error[ok], axis=0)
            print(f"  pose_sigma {sigma:4.2f}: error left {np.sqrt((error[ok] ** 2).sum(1).mean()):.3f} px rms")


if __name__ == "__main__":
    main()
