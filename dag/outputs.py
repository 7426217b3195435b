"""What a run writes into its output folder besides the pictures its stages make: each drive's videos and
evaluation (kept when nothing they are made from changed), metrics.json, series.json and the report.
"""

from __future__ import annotations

import json
import logging
import posixpath
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from persona.stores import media, storage
from persona.stores.layout import Cast, Collection

from .context import RunContext
from .drive import write_videos
from .export import write_drive_glb
from .graph import outputs_key
from .report import write_run_report

log = logging.getLogger(__name__)


def drive_outputs(runner: RunContext, plan, speed: dict) -> dict:
    """A drive's videos (and a 3D drive's puppet.glb) and its evaluation, kept from the last run when nothing
    they are made from changed (:func:`kept_outputs`): ``outputs_key``, ``videos``, ``speed``,
    ``evaluation`` and the per-frame ``series`` of the report's plots."""
    drive = Collection(runner.root, plan.cast.drive)
    key = outputs_key(runner.wf, drive.provenance("composite/rgb"))
    kept = kept_outputs(plan.output, key)
    if kept is not None:
        log.info("%s: nothing new since its videos and evaluation were made: kept", plan.cast.drive)
        kept["speed"].update(speed)  # a drive made again (the same bytes) was timed again
        return kept
    out = {"outputs_key": key, "speed": {**last_speed(plan.output), **speed}}  # a drive not made again: its last timing
    stop = threading.Event()
    t0 = time.perf_counter()
    # the videos are encoded in this process while the workers evaluate: neither reads what the other makes, and
    # this process would otherwise only wait on the workers
    with ThreadPoolExecutor(1) as writer:
        videos = writer.submit(_videos, runner, plan, drive, stop)
        try:
            with runner.tasks.step("evaluate", plan.cast.drive), \
                    runner.tasks.progress_bar(f"{plan.cast.drive:>13} {'analyse':<10}", drive.n) as bar:
                evaluation = runner.evaluate(plan.cast, progress=bar.update)
        except BaseException:
            stop.set()  # the videos stop at their next shard, none of their files written
            raise
        out["speed"]["evaluate_seconds"] = time.perf_counter() - t0
        out["videos"] = videos.result()
    out["speed"]["outputs_seconds"] = time.perf_counter() - t0
    out["series"] = evaluation.pop("series")
    write_pictures(plan.output, evaluation.pop("pictures", {}))
    out["evaluation"] = evaluation
    return out


#: the pictures an evaluation makes, each written as NAME.png beside the videos when it makes it
EVALUATION_PICTURES = ("error_map",)


def write_pictures(output: str, pictures: dict[str, np.ndarray]) -> None:
    """An evaluation's ``pictures`` (:data:`EVALUATION_PICTURES`) into ``output``, and none left from an
    evaluation before that made one this one did not (a drive no longer judged as a self-reenactment)."""
    for name in EVALUATION_PICTURES:
        path = storage.join(output, f"{name}.png")
        if name in pictures:
            media.write_png(path, pictures[name])
        elif storage.isfile(path):
            storage.remove(path)


def _videos(runner: RunContext, plan, drive: Collection, stop: threading.Event) -> dict[str, str]:
    """A drive's videos (:func:`persona.dag.drive.write_videos`) and a 3D drive's puppet.glb (about 4 s for
    269 frames); none written once ``stop`` is set."""
    with runner.tasks.step("videos", plan.cast.drive):
        videos = write_videos(drive, Collection(runner.root, plan.cast.frames), plan.output, stop)
        if drive.has("mesh"):
            videos["glb"] = write_drive_glb(runner.root, plan.cast, storage.join(plan.output, "puppet.glb"))["path"]
    return videos


def kept_outputs(output: str, key: str) -> dict | None:
    """The videos, speed, evaluation and series a drive's last run left in ``output``, when they
    were made from the same frames and evaluation settings (its metrics.json, written last,
    records ``outputs_key``) and every video is still there; else None. A video is looked for in
    ``output`` under its own name, wherever metrics.json says it was written: a folder copied or moved
    elsewhere keeps its own videos, not the ones it was copied from."""
    metrics, series = storage.join(output, "metrics.json"), storage.join(output, "series.json")
    if not (storage.isfile(metrics) and storage.isfile(series)):
        return None
    last = json.loads(storage.read_text(metrics))
    videos = {k: str(storage.join(output, posixpath.basename(str(v)))) for k, v in last.get("videos", {}).items()}
    if last.get("outputs_key") != key or not all(storage.isfile(v) for v in videos.values()):
        return None
    return {**{k: last[k] for k in ("outputs_key", "speed", "evaluation")}, "videos": videos,
            "series": json.loads(storage.read_text(series))}


def last_speed(output: str) -> dict:
    """The drive's timings its last run left in ``output`` (its metrics.json's ``speed``; {} when there is
    none), which a run that evaluates again without making the drive's frames again keeps."""
    metrics = storage.join(output, "metrics.json")
    return json.loads(storage.read_text(metrics)).get("speed", {}) if storage.isfile(metrics) else {}


def write_outputs(runner: RunContext, output: str, report: dict, series: dict | None,
                  cast: Cast | None) -> None:
    """metrics.json, series.json (the report's plots, should it be made again) and report.html in ``output``."""
    if series is not None:
        write_json(storage.join(output, "series.json"), {k: np.asarray(v, float).tolist() for k, v in series.items()})
    write_json(storage.join(output, "metrics.json"), report)
    write_run_report(runner.wf, runner.root, report, series, cast=cast, output=output)


def write_json(path, data: dict) -> None:
    """A JSON file (a local path or a URL), written atomically."""
    media.write_bytes(path, json.dumps(data, indent=2, default=str).encode())
