"""Where a self-reenactment's remaining error lies: placement or appearance, and which features.

    .venv/bin/python benchmarks/self_reenactment_budget.py WORKFLOW [--drive NAME] [--every 4]

For every drive of a self-reenactment WORKFLOW (``evaluate: {self_reenactment: true}``; finished: its store
holds the composite), every ``--every``-th frame, the composite's PSNR / SSIM against the real frame over the
rendered face (as ``persona evaluate`` measures them), and the same after each of these, applied to the
composite alone:

- ``shift``: the whole face moved by one shift, the median of the optical flow (DIS) from the real frame to
  the composite over the face: about what a better placed head could give;
- ``warp h/40``, ``warp h/15``: the composite warped onto the real frame by that flow, smoothed by a Gaussian
  of 1/40 or 1/15 of the face's height: what placing every feature right would give, down to that scale; what
  is left is appearance (colour, shading, detail);
- ``real eyes``, ``real brows``, ``real mouth``: the real frame pasted where its eyes, brows or mouth are
  (the hull of their landmarks grown by 0.12 of the eye distance): what that feature's every error costs.

None of these can be done without the real frame; they bound what work on each part could give.
"""

from __future__ import annotations

import argparse

import numpy as np

#: the features pasted from the real frame: their iBUG landmarks, one hull per group
FEATURES = {"eyes": (range(36, 42), range(42, 48)), "brows": (range(17, 22), range(22, 27)),
            "mouth": (range(48, 60),)}
#: how far each feature's hull is grown, over the eye distance
GROW = 0.12
#: the flow's smoothing, over the face's height: features, and larger parts of the face
WARPS = (40, 15)


def variants(real: np.ndarray, composite: np.ndarray, mask: np.ndarray, points: np.ndarray) -> dict[str, np.ndarray]:
    """The composite (h, w, 3) uint8 as it is and after each change of the module's docstring, against the real
    frame ``real`` with its 68 landmarks ``points``; ``mask`` (h, w) bool, the rendered face."""
    import cv2

    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (real, composite)]
    rows = np.flatnonzero(mask.any(axis=1))
    height = float(rows[-1] - rows[0] + 1)
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(grey[0], grey[1], None)  # real(x) ~
    ys, xs = np.mgrid[:mask.shape[0], :mask.shape[1]].astype(np.float32)                               # comp(x + flow)

    def moved(by):
        return cv2.remap(composite, xs + by[..., 0], ys + by[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)

    out = {"as it is": composite, "shift": moved(np.broadcast_to(np.median(flow[mask], axis=0), flow.shape))}
    for part in WARPS:
        out[f"warp h/{part}"] = moved(cv2.GaussianBlur(flow, (0, 0), height / part))
    eyes = float(np.linalg.norm(points[36:42].mean(axis=0) - points[42:48].mean(axis=0)))
    reach = max(1, int(round(GROW * eyes)))
    for name, groups in FEATURES.items():
        region = np.zeros(mask.shape, np.uint8)
        for group in groups:
            cv2.fillConvexPoly(region, cv2.convexHull(np.round(points[list(group)]).astype(np.int32)), 1)
        region = cv2.dilate(region, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) > 0
        pasted = composite.copy()
        pasted[region] = real[region]
        out[f"real {name}"] = pasted
    return out


def budget(root, cast, every: int = 4) -> dict[str, tuple[float, float]] | None:
    """Per variant (:func:`variants`), the mean over every ``every``-th frame of the drive of ``cast`` of the PSNR
    and SSIM of the face region (evaluate.masked_psnr, masked_ssim; the render's mask over half); None when the
    store holds no composite for it."""
    from persona.dag.evaluate import driver_frame_landmarks
    from persona.plugins.builtin import evaluate as ev
    from persona.stores.layout import Collection

    drive, frames = Collection(root, cast.drive), Collection(root, cast.frames)
    if not drive.has("composite/rgb"):
        return None
    landmarks = driver_frame_landmarks(root, cast.frames)
    scores: dict[str, list] = {}
    for j in range(0, drive.n, every):
        mask = drive.array("render/mask")[j] > 127
        if not mask.any() or not np.isfinite(landmarks[j]).all():
            continue
        real = frames.array("photos/rgb")[j]
        for name, image in variants(real, drive.array("composite/rgb")[j], mask, landmarks[j]).items():
            scores.setdefault(name, []).append((ev.masked_psnr(image, real, mask), ev.masked_ssim(image, real, mask)))
    return {name: tuple(np.mean(values, axis=0)) for name, values in scores.items()} if scores else None


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workflow")
    ap.add_argument("--drive", help="only the drive of this name (default: every drive)")
    ap.add_argument("--every", type=int, default=4, help="every how many frames (default: 4)")
    args = ap.parse_args(argv)

    from persona.dag.workflow import load_workflow
    from persona.stores.layout import open_store

    wf = load_workflow(args.workflow)
    if not wf.evaluate.self_reenactment:
        raise SystemExit(f"{args.workflow}: not a self-reenactment (evaluate: {{self_reenactment: true}}): its drives' "
                         "real frames are not what their composites should be")
    root = open_store(wf.store, mode="r")
    for plan in wf.drive_plans():
        if args.drive and plan.name != args.drive:
            continue
        found = budget(root, plan.cast, args.every)
        if found is None:
            print(f"{plan.name}: no composite in the store (not run)")
            continue
        base = found["as it is"][0]
        print(f"{plan.name}, every {args.every}th frame: PSNR dB / SSIM of the face region")
        for name, (psnr, ssim) in found.items():
            gain = "" if name == "as it is" else f"  ({psnr - base:+.2f} dB)"
            print(f"  {name:<12} {psnr:6.2f} / {ssim:.3f}{gain}")


if __name__ == "__main__":
    main()
