"""``persona demo``: synthetic faces made on the spot, run through every stage.

Makes a puppet collection (actor B), a driver collection (actor A) and a driving
video of A, with ground-truth sidecars, writes a workflow for them, and runs it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from persona.plugins.face import synthetic
from persona.plugins.face.template import FaceIdentity
from persona.stores import media

from .runner import run_workflow
from .workflow import load_workflow


def write_collection(folder: Path, photos) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, photo in enumerate(photos):
        path = folder / f"photo{i:04d}.png"
        media.write_png(path, photo.image)
        media.write_landmark_sidecar(path, photo.landmarks)


def driver_identity(seed: int = 0) -> FaceIdentity:
    """The driver A of the demo: the identity of the driver's photos (the one ``make_collection``
    draws first from seed + 1), so that A's video shows the same person as A's photos."""
    return FaceIdentity.random(np.random.default_rng(seed + 1))


def make_demo_data(folder: Path, *, n_photos: int = 24, n_frames: int = 30, seed: int = 0) -> Path:
    """Write the synthetic data and a workflow for it into ``folder``; return the workflow path."""
    data = folder / "data"
    write_collection(data / "puppet", synthetic.make_collection(n_photos, seed=seed))
    write_collection(data / "driver", synthetic.make_collection(n_photos, seed=seed + 1))
    video = synthetic.make_driver_video(n_frames, seed=seed + 2, identity=driver_identity(seed))
    media.write_video_mp4(data / "driver.mp4", (frame.image for frame in video), fps=25)
    workflow = {
        "version": 1,
        "name": "demo",
        "store": "run.zarr",
        "output": "output",
        "puppet": {"photos": "data/puppet/*.png"},
        "driver": {"photos": "data/driver/*.png", "video": "data/driver.mp4"},
        "photos_per_shard": 8,
        # the synthetic cameras' focal length is known: twice the image's longer side
        "stages": {"pose": {"params": {"focal_factor": 2.0}}},
    }
    path = folder / "demo.yaml"
    path.write_text(yaml.safe_dump(workflow, sort_keys=False))
    return path


def run_demo(folder: Path, *, n_photos: int = 24, n_frames: int = 30, workers: int | None = None,
             scheduler: str | None = None, progress: bool = True) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "demo.yaml"
    if not path.exists():
        print(f"making synthetic faces in {folder / 'data'} ...")
        path = make_demo_data(folder, n_photos=n_photos, n_frames=n_frames)
    return run_workflow(load_workflow(path), scheduler=scheduler, workers=workers, progress=progress)
