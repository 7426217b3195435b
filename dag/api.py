"""Persona from Python: run a workflow, open what a run made.

``import persona`` gives these functions (the ``persona`` package itself is ``dag/_persona/``, see
pyproject.toml); the ``persona`` command goes through them too, so a notebook and the command line
run the same code and meet the same errors (every one a :class:`~persona.stores.errors.PersonaError`
that names the file and what to do)::

    import persona
    report = persona.run("workflows/fig8.yaml")          # or a dict, as the YAML file would hold
    run = persona.open("workflows/fig8.yaml")            # or persona.open("runs/fig8.zarr")
    run.people["bush"].dataset("aligned")                # an xarray Dataset of the aligned faces
    run.drives["bush_obama_address"].figures["amplitude"]

:func:`open` gives each person, video and drive of a store as a plain object: its counts and rejected
photos, its arrays as xarray datasets, its average mesh (people), its figures, videos and report
(drives; these live in the workflow's output folder, so open the workflow, or pass ``output=``) and
its glTF export (:mod:`persona.dag.export`). A walk-through: docs/api.md.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
import numpy as np

from persona.stores import storage
from persona.stores.errors import PersonaError, StorageError
from persona.stores.layout import Cast, Collection, StoreError, collections, open_store, rejections

from .workflow import Workflow, load_workflow, parse_workflow, set_override

__all__ = ["Drive", "Person", "Run", "Video", "open", "run", "workflow"]


def workflow(source: str | os.PathLike | dict | Workflow, overrides: list[str] = (), *,
             base_dir: str | os.PathLike | None = None) -> Workflow:
    """A validated workflow from a YAML file's path, a dict holding what the file would (relative paths
    resolve against ``base_dir``, by default the current folder) or a :class:`Workflow` as it is;
    ``overrides`` are ``--set`` assignments ("stages.landmarks.params.select=largest").
    Raises :class:`~persona.dag.workflow.WorkflowError` listing every error."""
    if isinstance(source, Workflow):
        if overrides:
            raise PersonaError("overrides apply to a workflow file or dict, not to a Workflow already validated: "
                               "pass the file or the dict instead")
        return source
    if isinstance(source, dict):
        data = copy.deepcopy(source)
        for assignment in overrides:
            set_override(data, assignment)
        return parse_workflow(data, source="<workflow dict>", base_dir=Path(base_dir or os.getcwd()))
    return load_workflow(source, list(overrides))


def run(source: str | os.PathLike | dict | Workflow, *, overrides: list[str] = (), scheduler: str | None = None,
        workers: int | None = None, progress: bool = True, force: bool = False) -> dict:
    """Run a workflow (:func:`workflow` takes ``source`` and ``overrides``) as ``persona run`` does, resuming
    what an earlier run left; returns the run's report (also in the output folder's metrics.json).

    ``scheduler``: "local", "sync" (everything in this process) or a Dask scheduler's address, replacing
    the workflow's cluster; ``force``: write into an output folder that holds files Persona did not write.
    A full disk is a :class:`~persona.stores.errors.StorageError` saying where to free space."""
    from .executor import disk_full
    from .runner import run_workflow

    wf = workflow(source, overrides)
    try:
        return run_workflow(wf, scheduler=scheduler, workers=workers, progress=progress, force=force)
    except OSError as exc:
        if not disk_full(exc):
            raise
        where = exc.filename or wf.store
        raise StorageError(f"the disk is full ({exc.strerror}) writing {where}: free space there "
                           f"({_free_space(where)}) or set store: / output: to a larger disk, then run again "
                           "(finished work is kept)") from None


def _free_space(path) -> str:
    """What is free on the disk of a local path, as people read it."""
    folder = os.path.dirname(os.path.abspath(str(path)))
    while folder and not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    try:
        return f"{shutil.disk_usage(folder).free / 2**20:.1f} MiB free in {folder}"
    except OSError:
        return "its free space unknown"


# -- what a store holds ----------------------------------------------------------------------------------

@dataclass
class _Part:
    """What a person, a video and a drive have in common: a collection of the store (photos or frames)."""

    name: str            #: the workflow's name for it ("bush"), or its store path in a version-1 store ("puppet")
    path: str            #: its group in the store ("people/bush")
    store: str = field(repr=False)
    collection: Collection = field(repr=False)

    @property
    def n(self) -> int:
        """Its photos or frames, accepted or not."""
        return self.collection.n

    @property
    def accepted(self) -> int:
        """Its photos or frames that got through every stage."""
        from .stages import accepted

        return int(accepted(self.collection).sum())

    @property
    def rejections(self) -> dict[str, list[str]]:
        """The ids of its rejected photos (or frames) by reason, the most common reason first."""
        return rejections(self.collection)

    def dataset(self, group: str = ""):
        """The arrays of its group (or of a sub-group: "aligned", "landmarks", "shape", "render") as an
        ``xarray.Dataset``, read lazily with Dask; each array's dimensions are named in the store."""
        try:
            import xarray as xr
        except ImportError:
            raise PersonaError("datasets need xarray: pip install xarray (Persona's dependencies include it; "
                               "reinstall Persona)") from None
        path = f"{self.path}/{group}" if group else self.path
        if path not in self.collection.root:
            raise StoreError(f"{self.store} has no group {path}: its groups are "
                             f"{', '.join(sorted(n for n, _ in self.collection.group.groups()))}")
        return xr.open_zarr(self.store, group=path, consolidated=False,
                            storage_options=storage.options(self.store) if storage.is_url(self.store) else None)


@dataclass
class Person(_Part):
    """A person's photos, aligned faces and average 3D face."""

    output: str | None = field(default=None, repr=False)

    @property
    def has_shape(self) -> bool:
        """Whether a 3D shape was made (a few photos, or photos in one light, make none)."""
        return self.collection.has("shape/depth")

    @property
    def mean_face(self) -> np.ndarray:
        """(H, W, 3) float32: the mean of its aligned faces on the canonical grid."""
        return self.collection.array("aligned/mean")[...]

    @property
    def texture(self) -> np.ndarray:
        """(H, W, 3) uint8: the average face's texture on the canonical grid (the OBJ's)."""
        return self.collection.array("shape/texture")[...]

    def mesh(self, step: int = 1):
        """The average 3D face as :class:`persona.plugins.animation.FaceMesh`: vertices in metres (origin
        between the eyes, x right, y up, z towards the viewer, as the OBJ), triangles, texture coordinates
        and the texture; ``step`` keeps every step-th grid point across and down."""
        from .export import person_mesh

        return person_mesh(self.collection, step=step)

    def glb(self, path: str | os.PathLike) -> Path | str:
        """Write the average face with its texture as a glTF 2.0 binary file (.glb) at ``path``."""
        from .export import write_person_glb

        return write_person_glb(self.collection, path)

    @property
    def files(self) -> dict[str, str]:
        """Its files in the output folder that exist: mesh (.obj, .ply, and .glb once `persona glb` wrote it),
        previews, mean face, contact sheet."""
        slug = self.path.replace("/", "_")
        names = {"mesh_obj": f"{slug}_mesh.obj", "mesh_ply": f"{slug}_mesh.ply", "mesh_glb": f"{slug}_mesh.glb",
                 "mesh_previews": f"{slug}_mesh_previews.png", "mean_face": f"{slug}_mean_face.png",
                 "contact_sheet": f"{slug}_contact_sheet.png"}
        return _existing(self.output, names)


@dataclass
class Video(_Part):
    """A driving video's frames, landmarked and posed."""

    @property
    def fps(self) -> float:
        return float(self.collection.attrs.get("fps", 25.0))

    @property
    def source(self) -> dict:
        """The video file and frame range the frames were read from."""
        return dict(self.collection.attrs.get("video", {}))


@dataclass
class Drive(_Part):
    """One puppet performing one video: the per-frame meshes, textures, renders and composites, and in
    the output folder its videos, figures and report."""

    cast: Cast = field(default_factory=Cast, repr=False)
    puppet: str = ""     #: the performing person's name (a key of :attr:`Run.people`)
    driver: str = ""     #: the driver's name
    video: str = ""      #: the video's name (a key of :attr:`Run.videos`)
    output: str | None = field(default=None, repr=False)  #: the drive's output folder, when known

    @property
    def fps(self) -> float:
        return float(self.collection.attrs.get("fps", 25.0))

    def _metrics(self) -> dict | None:
        if self.output is None:
            raise PersonaError(f"the output folder of {self.name} is not known: open the workflow "
                               "(persona.open('my.yaml')) or pass output= to persona.open")
        path = storage.join(self.output, "metrics.json")
        return json.loads(storage.read_text(path)) if storage.isfile(path) else None

    @property
    def figures(self) -> dict | None:
        """The evaluation's figures (as metrics.json has them), or None before the drive is evaluated."""
        metrics = self._metrics()
        return None if metrics is None else metrics.get("evaluation")

    @property
    def speed(self) -> dict | None:
        metrics = self._metrics()
        return None if metrics is None else metrics.get("speed")

    @property
    def videos(self) -> dict[str, str]:
        """Its videos that exist: composite, puppet (the face alone), side_by_side."""
        self._metrics()  # the same clear error when the output folder is not known
        return _existing(self.output, {name: f"{name}.mp4" for name in ("composite", "puppet", "side_by_side")})

    @property
    def files(self) -> dict[str, str]:
        """Its other files that exist: report.html, frames.png, metrics.json, puppet.glb and, judged as a
        self-reenactment, error_map.png."""
        self._metrics()
        return _existing(self.output, {"report": "report.html", "frames": "frames.png", "metrics": "metrics.json",
                                       "glb": "puppet.glb", "error_map": "error_map.png"})

    def glb(self, path: str | os.PathLike, *, step: int = 2) -> Path | str:
        """Write the puppet performing the video as an animated glTF 2.0 binary file (.glb) at ``path``:
        one morph target per frame at the video's rate, the head's pose as the animation of its node;
        ``step`` keeps every step-th vertex of the face grid across and down (docs/api.md gives sizes)."""
        from .export import write_drive_glb

        return write_drive_glb(self.collection.root, self.cast, path, step=step)


def _existing(folder, names: dict[str, str]) -> dict[str, str]:
    if folder is None:
        return {}
    paths = {key: storage.join(folder, name) for key, name in names.items()}
    return {key: str(path) for key, path in paths.items() if storage.isfile(path)}


@dataclass
class Run:
    """What a store holds: each person, video and drive by name."""

    store: str
    output: str | None
    people: dict[str, Person]
    videos: dict[str, Video]
    drives: dict[str, Drive]

    def __repr__(self) -> str:
        return (f"Run(store={self.store!r}, output={self.output!r}, people={sorted(self.people)}, "
                f"videos={sorted(self.videos)}, drives={sorted(self.drives)})")


#: the groups of a version-2 store, and what each holds
_KINDS = {"people": Person, "videos": Video, "drives": Drive}


def open(source: str | os.PathLike | dict | Workflow, *, output: str | os.PathLike | None = None) -> Run:  # noqa: A001
    """Open a run: a workflow (its YAML file, dict or :class:`Workflow`: its store and output folder) or a
    store's path or URL (then its output folder, for the figures and videos, is ``output`` if given).
    Raises :class:`~persona.stores.layout.StoreError` when there is no Persona store there."""
    wf = None
    if isinstance(source, (dict, Workflow)) or str(source).endswith((".yaml", ".yml")):
        wf = workflow(source)
        store, output = wf.store, wf.output
    else:
        store = source
    store = str(store)
    root = open_store(store, mode="r")
    out = None if output is None else str(output)
    found: dict[str, dict] = {kind: {} for kind in _KINDS}
    for c in collections(root):
        kind, _, name = c.path.partition("/")
        if kind in _KINDS and name:  # version 2: people/<name>, videos/<name>, drives/<name>
            found[kind][name] = c
        elif c.path in ("puppet", "driver"):  # version 1, keyed by store path
            found["people"][c.path] = c
        elif c.path == "driver/frames":
            found["videos"][c.path] = c
        elif c.path == "drive":
            found["drives"][c.path] = c
    people = {name: Person(name, c.path, store, c, output=out) for name, c in found["people"].items()}
    videos = {name: Video(name, c.path, store, c) for name, c in found["videos"].items()}
    drives = {}
    for name, c in found["drives"].items():
        cast = Cast.of(root, c.path)
        folder = None if out is None else (out if c.path == "drive" else str(storage.join(out, name)))
        if wf is not None:  # the workflow says where each drive's output goes
            folder = next((str(p.output) for p in wf.drive_plans() if p.cast.drive == c.path), folder)
        drives[name] = Drive(name, c.path, store, c, cast=cast, puppet=_name(cast.puppet), driver=_name(cast.driver),
                             video=_name(cast.frames), output=folder)
    return Run(store, out, people, videos, drives)


def _name(path: str) -> str:
    kind, _, name = path.partition("/")
    return name if kind in _KINDS and name else path

