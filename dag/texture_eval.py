"""``persona evaluate --texture``: leave-one-out scores of texture synthesis (paper Fig. 5).

Reference photos are held out of the collection; for each, every method synthesizes the
person's face with the reference's expression (its pose-corrected fiducials, and the
reference itself for the paper's reference-mode flow), from the other photos only:

- alignment: dlib's landmarks found on the synthesized face against the reference's
  fiducials, median error over the 49 points, % of the inter-ocular distance;
- detail: band-pass energy (difference of Gaussians, σ 1 and 4 px) of the result over the
  reference's, on the inner face (1 = as sharp as a real photo);
- fidelity: SSIM of the two band-pass images (low frequencies are averaged out by design);
- colour consistency: the spread (relative standard deviation, %) over all references of
  the result's mean face colour (lower is more consistent).

Medians of two methods can hide how they compare reference by reference, so the alignment
errors are also compared in pairs: ours minus each other method, on the same references.

Dask tasks of a few references each; a worker builds the collection once and keeps it.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from persona.plugins.builtin.evaluate import masked_ssim
from persona.plugins.builtin.landmarks import DlibLandmarks
from persona.plugins.base import Rejected
from persona.plugins.face.template import IDX49, generic_template
from persona.plugins.face.texture import bandpass as texture_bandpass
from persona.plugins.face.warp import eye_mouth_scale
from persona.stores import media, storage
from persona.stores.layout import Collection, open_store

from . import stages as st
from .outputs import write_json
from .texture import texture_photos

#: the paper's Fig. 5 columns: (ii) static, (iii) weighted, (iv) prewarped, ours
METHODS = ("static", "weighted", "prewarped", "multiscale")
LABELS = {"reference": "reference", "static": "(ii) static", "weighted": "(iii) weighted",
          "prewarped": "(iv) prewarped", "multiscale": "ours"}
PAD = 60  # grey border around a canonical face so the HOG detector finds it


@lru_cache(maxsize=1)
def _collection(url: str, path: str, rows: tuple[int, ...]):
    return texture_photos(Collection(open_store(url, mode="r"), path), np.array(rows))


@lru_cache(maxsize=1)
def _inner_face() -> np.ndarray:
    return cv2.erode(generic_template().mask.astype(np.uint8), np.ones((21, 21), np.uint8)) > 0


def bandpass(rgb: np.ndarray) -> np.ndarray:
    """The band-pass of the alignment's misfit measure (σ 1 and 4 px) on the mean grey."""
    return texture_bandpass(np.asarray(rgb, np.float32).mean(axis=-1))


def landmark_error(rgb: np.ndarray, fiducials: np.ndarray, detector: DlibLandmarks) -> float:
    """Median distance of dlib's 49 fiducials on a canonical face to ``fiducials`` (their visible ones), % of the
    inter-ocular distance; NaN when dlib finds no face."""
    canvas = cv2.copyMakeBorder(np.clip(rgb, 0, 255).astype(np.uint8), PAD, PAD, PAD, PAD,
                                cv2.BORDER_CONSTANT, value=(128, 128, 128))
    try:
        found = detector.detect(canvas).points[list(IDX49)] - PAD
    except Rejected:
        return float("nan")
    return float(100 * np.nanmedian(np.linalg.norm(found - fiducials, axis=1)) / eye_mouth_scale(fiducials)[0])


def scores(result: np.ndarray, result_mask: np.ndarray, reference_band: np.ndarray, reference_mask: np.ndarray,
           fiducials: np.ndarray, detector: DlibLandmarks) -> dict:
    """The per-reference figures of one synthesized face (see the module's docstring);
    ``reference_band`` is :func:`bandpass` of the reference."""
    mask = _inner_face() & result_mask & reference_mask
    a, b = bandpass(result), reference_band
    span = float(np.percentile(b[mask], 99) - np.percentile(b[mask], 1))
    shift = lambda x: np.clip(128 + 127 * x / span, 0, 255).astype(np.uint8)  # noqa: E731
    return {"alignment": landmark_error(result, fiducials, detector),
            "detail": float(np.mean(a[mask] ** 2) / np.mean(b[mask] ** 2)),
            "fidelity": masked_ssim(shift(a), shift(b), mask),
            "colour": result[mask].mean(axis=0).tolist()}


def evaluate_references(url: str, path: str, rows: tuple[int, ...], references: list[int],
                        methods: dict[str, dict], pictures: set[int], use_reference: bool = True) -> list[dict]:
    """Dask task: every method on each reference, from the collection ``rows``; the target is the
    reference photo (the paper's reference mode) or, without ``use_reference``, its fiducials only.
    Each method aligns with the flow its params name."""
    coll = Collection(open_store(url, mode="r"), path)
    photos = _collection(url, path, rows)
    registry = st.default_registry()
    backends = {name: registry.get("texture", name)(params) for name, params in methods.items()}
    detector = DlibLandmarks()
    fiducials = coll.array("aligned/fiducials")[:].astype(np.float64)
    out = []
    for r in references:
        reference, seen = coll.array("aligned/rgb")[r], coll.array("aligned/mask")[r]
        band = bandpass(reference)
        row = {"photo": int(r), "reference_alignment": landmark_error(reference, fiducials[r], detector),
               "methods": {}, "images": {}}
        for name, backend in backends.items():
            texture = backend.synthesize(photos, fiducials[r], reference=reference if use_reference else None)
            row["methods"][name] = scores(texture.rgb, texture.mask, band, seen, fiducials[r], detector)
            if r in pictures:
                row["images"][name] = np.clip(texture.rgb, 0, 255).round().astype(np.uint8)
        if r in pictures:
            row["images"]["reference"] = reference
        out.append(row)
    return out


def summarize(rows: list[dict]) -> dict:
    """Per method: median alignment error (and faces dlib missed), median detail and fidelity,
    and the colour spread over references."""
    table = {}
    for name in rows[0]["methods"]:
        figures = [r["methods"][name] for r in rows]
        colours = np.array([f["colour"] for f in figures])
        alignment = np.array([f["alignment"] for f in figures])
        table[name] = {
            "alignment_median_pct_iod": float(np.nanmedian(alignment)) if np.isfinite(alignment).any() else None,
            "no_face_found": int(np.isnan(alignment).sum()),
            "detail_median": float(np.median([f["detail"] for f in figures])),
            "fidelity_median": float(np.median([f["fidelity"] for f in figures])),
            "colour_spread_pct": float(100 * np.mean(colours.std(axis=0) / colours.mean(axis=0)))}
    reference = np.array([r["reference_alignment"] for r in rows])
    table["reference"] = {"alignment_median_pct_iod": float(np.nanmedian(reference)),
                          "no_face_found": int(np.isnan(reference).sum())}
    return table


def paired(rows: list[dict], ours: str = "multiscale") -> dict:
    """Alignment error of ``ours`` minus each other method's, reference by reference (where dlib
    found both faces): median, mean and its standard error (% IOD), and how often ours is lower.
    Negative is better for ours."""
    out = {}
    if ours not in rows[0]["methods"]:
        return out
    for name in (m for m in rows[0]["methods"] if m != ours):
        d = np.array([r["methods"][ours]["alignment"] - r["methods"][name]["alignment"] for r in rows])
        d = d[np.isfinite(d)]
        if len(d) == 0:
            continue
        out[name] = {"median": float(np.median(d)), "mean": float(d.mean()),
                     "standard_error": float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else None,
                     "ours_better": int((d < 0).sum()), "references": len(d)}
    return out


def grid(rows: list[dict]) -> np.ndarray:
    """Fig. 5 as a picture: one row per reference, columns reference | ii | iii | iv | ours."""
    columns = ["reference", *[m for m in METHODS if m in rows[0]["images"]]]
    h, w = rows[0]["images"]["reference"].shape[:2]
    header = np.full((28, w * len(columns), 3), 255, np.uint8)
    for j, name in enumerate(columns):
        cv2.putText(header, LABELS[name], (j * w + 6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    body = [np.concatenate([r["images"][c] for c in columns], axis=1) for r in rows if r["images"]]
    return np.concatenate([header, *body], axis=0)


def evaluate_texture(runner, path: str = "puppet", *, references: int = 40, seed: int = 0,
                     methods: tuple[str, ...] = METHODS, pictures: int = 8, photos: int | None = None,
                     mode: str = "reference") -> dict:
    """Hold out ``references`` random accepted photos of collection ``path``, synthesize each
    with every method from the others (or from ``photos`` of them drawn at random), score; write
    the grid PNG and a JSON table into the run's output folder. ``mode``: "reference" gives the
    methods the reference photo itself (the paper's Fig. 5; ``prewarped`` and ``multiscale`` then
    flow to its actual geometry), "fiducials" only its 49 fiducials (as in puppetry)."""
    if mode not in ("reference", "fiducials"):
        raise ValueError(f"mode must be 'reference' or 'fiducials', got {mode!r}")
    coll = Collection(runner.root, path)
    ok = np.flatnonzero(st.accepted(coll))
    if len(ok) < references + 8:
        raise Rejected(f"{path}: {len(ok)} accepted photos; need more than {references} references + 8")
    chosen = np.sort(np.random.default_rng(seed).choice(ok, references, replace=False))
    rest = np.setdiff1d(ok, chosen)
    if photos is not None and photos < len(rest):
        rest = np.sort(np.random.default_rng(seed + 1).choice(rest, photos, replace=False))
    rows = tuple(int(i) for i in rest)
    ours, ours_params = runner.wf.stage("texture")
    shared = {"flow": ours_params["flow"]} if "flow" in ours_params else {}  # the baselines align as ours does
    params = {m: ours_params if m == ours else
              {k: v for k, v in shared.items() if k in st.default_registry().get("texture", m).Params.model_fields}
              for m in methods}
    shown = {int(i) for i in chosen[:pictures]}
    parts = np.array_split(chosen, -(-len(chosen) // 4))  # small tasks: progress, and balance across workers
    tasks = [(runner.wf.store, path, rows, [int(i) for i in part], params, shown, mode == "reference")
             for part in parts]
    results = []
    with runner.tasks.progress_bar(f"{path:>13} texture evaluation", len(chosen), unit="reference") as bar:
        for part in runner.executor.run(evaluate_references, tasks):
            results += part
            bar.update(len(part))
    results.sort(key=lambda row: row["photo"])
    table = summarize(results)
    out = runner.wf.output
    slug, suffix = path.replace("/", "_"), "" if mode == "reference" else "_fiducials"
    grid_file = storage.join(out, f"{slug}_texture_grid{suffix}.png")
    media.write_png(grid_file, grid(results))
    report = {"collection": path, "mode": mode, "references": [int(i) for i in chosen], "collection_photos": len(rows),
              "methods": params, "table": table,
              "paired_alignment": paired(results),
              "per_reference": [{k: v for k, v in r.items() if k != "images"} for r in results],
              "grid": str(grid_file)}
    write_json(storage.join(out, f"{slug}_texture_evaluation{suffix}.json"), report)
    return report
