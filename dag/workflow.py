"""Workflows: YAML files validated into strict pydantic models.

Validation reports every error at once, each with its YAML path, and suggests the
nearest valid name for misspelt keys, stage kinds and backend names. Relative paths
resolve against the workflow file's folder.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, field_validator, model_validator

from persona.plugins.face.dynamics import POSE_SIGMA, DynamicsParams
from persona.plugins.manager import FlowChoice, Registry, default_registry, did_you_mean
from persona.stores.media import MAX_PIXELS, MAX_SIDE, MIN_SIDE
from persona.stores import storage
from persona.stores.errors import PersonaError
from persona.stores.layout import Cast


class WorkflowError(PersonaError, ValueError):
    """A workflow file is invalid. ``errors`` lists (yaml path, message) pairs."""

    def __init__(self, source: str, errors: list[tuple[str, str]]):
        self.source = source
        self.errors = errors
        lines = [f"{source}: {len(errors)} error{'s' if len(errors) != 1 else ''}"]
        lines += [f"  {path or '(top level)'}: {msg}" for path, msg in errors]
        super().__init__("\n".join(lines))


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class VideoRange(Strict):
    """Frames ``start:stop:step`` of a video."""

    video: str = Field(description="path of the video file")
    start: int = Field(0, ge=0, description="first frame (0-based)")
    stop: int | None = Field(None, ge=1, description="frame after the last one; none = to the end")
    step: int = Field(1, ge=1, description="take every step-th frame")


PhotoSpec = Union[str, VideoRange, list[Union[str, VideoRange]]]


class Actor(Strict):
    photos: PhotoSpec = Field(description="a folder, a glob, a photo, a video, {video, start, stop, step}, or a "
                              "list mixing any of these (e.g. several videos: the paper builds collections "
                              "from many films)")
    video: Union[str, VideoRange, None] = Field(None, description="the actor's driving video (driver only)")


class Person(Strict):
    photos: PhotoSpec = Field(description="a folder, a glob, a photo, a video, {video, start, stop, step}, or a "
                              "list mixing any of these")


VideoSpec = Union[str, VideoRange]


class DriveSpec(Strict):
    puppet: Union[str, list[str]] = Field(description="the person (or people) performing: names under people")
    driver: str = Field(description="the person whose video drives them: a name under people (the driver's model "
                        "is built from that person's photos)")
    video: Union[VideoSpec, list[VideoSpec]] = Field(description="the driving video(s) of the driver: a video "
                                                     "file or {video, start, stop, step}, or a list of them")

    def puppets(self) -> list[str]:
        return self.puppet if isinstance(self.puppet, list) else [self.puppet]

    def videos(self) -> list[VideoSpec]:
        return self.video if isinstance(self.video, list) else [self.video]


def _frames(spec: VideoSpec) -> tuple:
    """(path, start, stop, step) of a video or a range of one: a video and its whole range are the same frames."""
    return (spec, 0, None, 1) if isinstance(spec, str) else (spec.video, spec.start, spec.stop, spec.step)


def video_name(spec: VideoSpec) -> str:
    """A driving video's name in a version-2 store: its file's stem, and the range when it has one
    (``address_0-900-10``, ``address_300-end``); characters other than letters, digits, ``-`` and ``_`` become ``_``."""
    path, start, stop, step = _frames(spec)
    extra = "" if (start, stop, step) == (0, None, 1) else (
        f"_{start}-{'end' if stop is None else stop}" + (f"-{step}" if step != 1 else ""))
    return re.sub(r"[^A-Za-z0-9_-]", "_", storage.name(storage.with_suffix(path, "")) + extra)


@dataclass(frozen=True)
class CollectionPlan:
    """A collection the workflow builds: its store path, its photos, whether it is a driving video's
    frames (no 3D shape) and whether it is a puppet (its expression-dependent texture is built)."""

    path: str
    photos: Any
    video: bool
    texture: bool


@dataclass(frozen=True)
class DrivePlan:
    """One drive of the workflow: its name, where its collections are (:class:`Cast`) and its output folder."""

    name: str
    cast: Cast
    output: str


class StageConfig(Strict):
    backend: str | None = Field(None, description="backend name; default: the kind's default backend")
    params: dict[str, Any] = Field(default_factory=dict, description="the backend's parameters")


class TLS(Strict):
    """This machine's certificate for a scheduler that speaks TLS (``tls://`` addresses): the
    scheduler and every worker then check each other's certificates against ``ca_file`` and talk
    encrypted, so only holders of a certificate the CA signed can send the scheduler code to run
    (docs/cluster.md, Security)."""

    ca_file: str = Field(description="the certificate authority's certificate (PEM) that signed the scheduler's, "
                         "the workers' and this one")
    cert: str = Field(description="this machine's certificate (PEM)")
    key: str = Field(description="its private key (PEM)")


class Cluster(Strict):
    """Where the Dask workers run: a local cluster (default), an existing scheduler, or worker jobs
    submitted to a batch scheduler (SLURM, PBS, SGE, LSF) through dask-jobqueue (docs/cluster.md)."""

    kind: Literal["local", "slurm", "pbs", "sge", "lsf"] = Field(
        "local", description='"local": workers on this machine (or the `scheduler` given); "slurm", "pbs", '
        '"sge", "lsf": Persona runs the scheduler in its own process and submits `jobs` batch jobs of Dask '
        "workers (dask-jobqueue); worker nodes need Persona installed and must reach the store")
    scheduler: str = Field("local", description='"local" (a local Dask cluster), "sync" (no cluster: '
                           'everything in this process, for debugging) or the address of an existing '
                           'dask.distributed scheduler, e.g. tcp://10.0.0.5:8786')
    workers: int | None = Field(None, ge=1, description="local workers (default: one per core)")
    threads_per_worker: int = Field(1, ge=1, description="threads per local worker")
    memory_limit: str = Field("auto", description='memory per local worker, e.g. "2GiB"')
    builds: int = Field(2, ge=1, description="version 2: how many people and videos are built at once, their "
                        "tasks sharing the workers (one's single-task steps, such as the 3D shape, leave the "
                        "other workers to the next's photos); 1 = one after another. The scheduler \"sync\" "
                        "builds one at a time")
    # batch kinds
    jobs: int = Field(1, ge=1, description="batch jobs of workers to submit (batch kinds)")
    cores: int = Field(1, ge=1, description="cores per batch job; each runs one single-threaded worker process")
    memory: str = Field("4GiB", description='memory per batch job, e.g. "16GiB", shared by its worker processes')
    queue: str | None = Field(None, description="queue (SLURM: partition) of the jobs; default: the "
                              "batch scheduler's default")
    account: str | None = Field(None, description="account the jobs are charged to (SLURM, PBS: account; SGE, LSF: "
                                "project)")
    walltime: str = Field("01:00:00", description='time limit of each job, "HH:MM:SS": a run that outlives '
                          "its workers stops and resumes when run again")
    job_extra_directives: list[str] = Field(default_factory=list, description='more directives for the job '
                                            'script, e.g. ["--constraint=avx2"] (SLURM) or ["-l mem=4gb"] (PBS)')
    job_script_prologue: list[str] = Field(default_factory=list, description="shell lines the job runs before "
                                           'the worker, e.g. ["module load python", "source ~/persona/.venv/bin/activate"]')
    host: str | None = Field(None, description="address the scheduler listens on, which the worker nodes must "
                             "reach (batch kinds). It runs pickled code sent to it: give a private address. "
                             "Default: the address of this machine's hostname (never 0.0.0.0); the dashboard "
                             "listens on 127.0.0.1")
    log_directory: str | None = Field(None, description="where the worker jobs write their logs "
                                      "(batch kinds); default: OUTPUT/worker-logs")
    start_timeout: float = Field(600, gt=0, description="seconds to wait for the first worker of the batch jobs "
                                 "to join before the run stops with the job ids (they may still be queued)")
    tls: TLS | None = Field(None, description="certificates for a scheduler address of tls://: encrypted, and "
                            "only machines with a certificate of the same CA get in (docs/cluster.md)")

    @field_validator("scheduler")
    @classmethod
    def _scheduler(cls, v: str) -> str:
        if v not in ("local", "sync") and "://" not in v:
            raise ValueError(f'"{v}" is neither "local", "sync" nor a scheduler address such as tcp://host:8786')
        return v

    @field_validator("memory")
    @classmethod
    def _memory(cls, v: str) -> str:
        from dask.utils import parse_bytes

        try:
            parse_bytes(v)
        except ValueError:
            raise ValueError(f'"{v}" is not an amount of memory such as "4GiB" or "16GB"') from None
        return v

    @model_validator(mode="after")
    def _one_scheduler(self) -> "Cluster":
        if self.kind != "local" and self.scheduler != "local":
            raise ValueError(f'kind "{self.kind}" starts its own scheduler; scheduler "{self.scheduler}" connects '
                             "to an existing one: give one of the two")
        if problem := tls_problem(self.scheduler, self.tls):
            raise ValueError(problem)
        return self


def tls_problem(scheduler: str, tls: TLS | None) -> str | None:
    """What is wrong with a scheduler address and the certificates given for it, or None: a tls://
    address needs them, and they serve no other."""
    if tls is not None and not scheduler.startswith("tls://"):
        return f'tls is for a scheduler address of tls://HOST:PORT, not "{scheduler}"'
    if scheduler.startswith("tls://") and tls is None:
        return f'"{scheduler}" speaks TLS: give this machine\'s certificate as cluster.tls {{ca_file, cert, key}}'
    return None


class StorageOptions(Strict):
    """How to reach the object storage of ``s3://`` URLs (store, photos, videos, output). What is left
    unset comes from the standard AWS environment variables (AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID,
    AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION) or ~/.aws. Key and secret are never written into the
    store, metrics or report (and print as '**********')."""

    endpoint_url: str | None = Field(None, description="an S3-compatible server, e.g. http://127.0.0.1:9000 "
                                     "(MinIO) or https://s3.eu-central-1.amazonaws.com; none = AWS")
    region: str | None = Field(None, description="the bucket's region, e.g. eu-central-1")
    key: SecretStr | None = Field(None, description="access key id (better: AWS_ACCESS_KEY_ID)")
    secret: SecretStr | None = Field(None, description="secret access key (better: AWS_SECRET_ACCESS_KEY)")
    anon: bool = Field(False, description="no credentials at all: a public bucket")

    @field_validator("endpoint_url")
    @classmethod
    def _endpoint(cls, v: str | None) -> str | None:
        if v is not None and not v.startswith(("http://", "https://")):
            raise ValueError(f'"{v}" is not an http:// or https:// address, e.g. http://127.0.0.1:9000')
        return v

    def fsspec(self) -> dict:
        """s3fs's keyword arguments (secrets revealed: for :func:`persona.stores.storage.configure` only)."""
        options: dict[str, Any] = {"anon": True} if self.anon else {}
        if self.endpoint_url:
            options["endpoint_url"] = self.endpoint_url
        if self.region:
            options["client_kwargs"] = {"region_name": self.region}
        if self.key is not None:
            options["key"] = self.key.get_secret_value()
        if self.secret is not None:
            options["secret"] = self.secret.get_secret_value()
        return options


class Evaluation(Strict):
    threshold: float = Field(0.6, gt=0, description="descriptor distance under which two faces are the same person")
    collection_sample: int = Field(100, ge=1, description="photos per collection whose descriptors make its centroid")
    identity_frames: int = Field(100, ge=0, description="output frames, evenly spaced, whose face descriptors judge "
                                 "identity (dlib's descriptor is most of the evaluation's time; 100 frames count "
                                 "the 'B and not A' fraction in steps of 1 %); 0 = every frame. The landmarks, and "
                                 "every other figure, take every frame. A drive whose puppet is its driver (a "
                                 "self-reenactment from one collection) is not judged for identity: B is A")
    self_reenactment: bool = Field(False, description="B and A are the same person and A's frames are not in "
                                   "B's collection: also compare the output with A's real frames (PSNR, SSIM)")


class Workflow(Strict):
    version: Literal[1, 2] = Field(1, description="workflow format version: 1, one puppet, one driver, one video "
                                   "(puppet, driver); 2, many people built once and every drive of them (people, drives)")
    name: str = Field(description="a short name for the run")
    store: str = Field(description="the Zarr store of the run (folder or fsspec URL, e.g. s3://bucket/run.zarr)")
    output: str = Field(description="folder (or URL, e.g. s3://bucket/run) for the pictures, videos and reports "
                        "people open")
    storage_options: StorageOptions = Field(default_factory=StorageOptions, description="how to reach object "
                                            "storage (s3:// URLs); unset: the AWS environment variables")
    puppet: Actor | None = Field(None, description="(version 1) actor B, whose face is built")
    driver: Actor | None = Field(None, description="(version 1) actor A, whose video drives the puppet")
    people: dict[str, Person] = Field(default_factory=dict, description="(version 2) every person by name, each "
                                      "built once whatever uses it")
    drives: list[DriveSpec] = Field(default_factory=list, description="(version 2) each puppet (or list of them) "
                                    "performing each of a driver's videos; a drive's outputs go to OUTPUT/<its name>")
    stages: dict[str, StageConfig] = Field(default_factory=dict, description="backend and params per kind")
    cluster: Cluster = Field(default_factory=Cluster)
    evaluate: Evaluation = Field(default_factory=Evaluation, description="how `persona evaluate` judges the output")
    photos_per_shard: int = Field(16, ge=1, le=4096, description="photos per Zarr shard: the unit of work and of writing")

    #: the folder relative paths were resolved against (not part of the YAML)
    base_dir: str = Field(".", exclude=True, description="(internal) folder of the workflow file")

    def collections(self) -> list[CollectionPlan]:
        """Every collection the workflow builds, each once, in the order they are built."""
        if self.version == 1:
            out = [CollectionPlan("puppet", self.puppet.photos, video=False, texture=True)]
            if self.driver is not None:
                out.append(CollectionPlan("driver", self.driver.photos, video=False, texture=False))
                if self.driver.video is not None:
                    out.append(CollectionPlan("driver/frames", self.driver.video, video=True, texture=False))
            return out
        puppets = {name for d in self.drives for name in d.puppets()}
        out = [CollectionPlan(f"people/{name}", person.photos, video=False, texture=name in puppets)
               for name, person in self.people.items()]
        return out + [CollectionPlan(path, spec, video=True, texture=False) for path, spec in self._videos()]

    def _videos(self) -> list[tuple[str, VideoSpec]]:
        """(store path, spec) of every distinct driving video of a version-2 workflow, in order of first use."""
        out: list[tuple[str, VideoSpec]] = []
        for d in self.drives:
            for video in d.videos():
                if all(_frames(spec) != _frames(video) for _, spec in out):
                    name = video_name(video)
                    taken = sum(path == f"videos/{name}" or path.startswith(f"videos/{name}~") for path, _ in out)
                    out.append((f"videos/{name}" + (f"~{taken + 1}" if taken else ""), video))
        return out

    def drive_plans(self) -> list[DrivePlan]:
        """Every drive: its name, its :class:`Cast` (where its collections are in the store) and its
        output folder. Version 1: one drive, ``drive``, into ``output`` (none without a video);
        version 2: each puppet of each drive with each of its videos, into ``output/<name>``."""
        if self.version == 1:
            return [DrivePlan("drive", Cast(), self.output)] if self.driver and self.driver.video is not None else []
        videos = self._videos()
        out: dict[str, DrivePlan] = {}
        for d in self.drives:
            for puppet in d.puppets():
                for video in d.videos():
                    path = next(p for p, spec in videos if _frames(spec) == _frames(video))
                    name = f"{puppet}_{d.driver}_{path.removeprefix('videos/')}"
                    out[name] = DrivePlan(name, Cast(f"people/{puppet}", f"people/{d.driver}", path, f"drives/{name}"),
                                          storage.join(self.output, name))
        return list(out.values())

    def stage(self, kind: str, registry: Registry | None = None) -> tuple[str, dict]:
        """(backend name, validated params as a dict) for a kind, defaults filled in."""
        registry = registry or default_registry()
        config = self.stages.get(kind, StageConfig())
        name = config.backend or registry.default(kind)
        params = registry.get(kind, name).Params.model_validate(config.params)
        return name, params.model_dump(mode="json")

    def backendless(self, kind: str) -> dict:
        """The validated params, defaults filled in, of a kind without backends (``BACKENDLESS``)."""
        config = self.stages.get(kind)
        return BACKENDLESS[kind].model_validate(config.params if config else {}).model_dump()


# Stage kinds that take params but no backend choice (their work lives in the DAG).
class IngestParams(Strict):
    max_side: int = Field(MAX_SIDE, ge=64, description="photos and video frames larger than this (px, longer "
                          "side) are downscaled; 1920 keeps a 1080p clip at its own size, so the output videos "
                          "are the driver's")
    max_pixels: int = Field(MAX_PIXELS, ge=1, description="headers claiming more pixels are rejected "
                            "as decompression bombs without decoding")
    min_side: int = Field(MIN_SIDE, ge=1, description="photos smaller than this (px, shorter side) are rejected")


class ScreenParams(Strict):
    max_distance: float = Field(16.0, gt=0, description="reject a frontalized photo whose visible fiducials "
                                "lie further than this from the collection's median shape (RMS over the "
                                "points, canonical px; the inter-ocular distance is 64): its landmarks or "
                                "pose failed. Every photo and frame of the example workflows' collections, "
                                "turned and laughing ones included, lies within 11 px (docs/fiducials.md)")


class AlignParams(Strict):
    rank: int = Field(4, ge=1, le=16, description="rank k of the appearance subspace (paper: 4, the "
                      "dimension of Lambertian faces under first-order spherical-harmonic light)")
    tps_lambda: float = Field(10.0, ge=0, description="λ of the smoothing TPS to the mean fiducials (Eq. 1; paper: 10)")


class CorrespondenceParams(FlowChoice):
    """The driver <-> puppet correspondence φ (paper §4, ALGORITHMS §7.3): B's 2D average projected
    onto A's rank-4 subspace, then a flow between the two.

    The paper used Liu's flow with (α, ratio, minWidth, outer, inner, SOR) = (0.02, 0.85, 20, 4, 1,
    40): ``backend: liu`` with its defaults. The default here, ``varref`` started from the landmark
    guide and pinned to the fiducials, and what it was chosen against: docs/expression.md."""

    landmark_guide: bool = Field(True, description="start from the smoothing TPS that takes B's mean fiducials "
                                 "to A's and let the flow correct it (A's basis is warped by the TPS before "
                                 "the projection); off = the flow alone, as in the paper")
    guide_lambda: float = Field(10.0, ge=0, description="λ of the guide's smoothing TPS (Eq. 1; paper: 10)")
    pin_fiducials: bool = Field(True, description="after the flow, add the smoothing TPS of φ's misses at B's "
                                "mean fiducials, so that φ takes each of them onto A's: the flow between two "
                                "blurred averages drifts at the thin lips (not in the paper; docs/expression.md)")
    pin_lambda: float = Field(1.0, ge=0, description="λ of the pinning TPS (Eq. 1's units): 0 interpolates")


class MotionParams(Strict):
    pose_sigma: float = Field(POSE_SIGMA, ge=0, le=10, description="σ (frames) of the Gaussian smoothing of the "
                              "driver's head pose over time (ALGORITHMS §9.2.1; not in the paper); 0 = none. "
                              "0.75 and more lagged a head that moves unevenly from frame to frame (docs/expression.md)")
    steady: int = Field(2, ge=0, le=10, description="frames on each side whose landmarks, carried into a frame "
                        "by optical flow, are averaged with its own before they drive the puppet, so the "
                        "detector's jitter averages down but not the face's motion (persona.plugins.face.tracks."
                        "steadied; not in the paper, 0 = off). 2 took the jitter of the drives by the woman from "
                        "1.00 to 0.94 on the face alone, the texture's change 0.12-0.13 to 0.08, and cost Bush's "
                        "eye gain 0.02 (docs/expression.md)")
    lips: Literal["mean", "parted", "closed"] = Field(
        "parted", description="how the driver's lips move the puppet's (retargeting): 'mean', the paper's, by the "
        "driver's offsets about the puppet's mean mouth; 'closed', the driver's own gap between the inner lips, "
        "scaled, so that its closed lips close the puppet's; 'parted' (not in the paper), the paper's but never less "
        "open than 'closed': a driver whose mean mouth is more open than the puppet's (one who smiles or talks "
        "through the clip) no longer shuts the puppet's lips while its own are apart (docs/expression.md)")
    widen: Literal["opening", "face"] = Field(
        "face", description="how far the puppet's eyes open wider than their neutral when the driver's do "
        "(retargeting): 'opening', by the ratio of the two faces' eye openings, as they close; 'face' (not in the "
        "paper), by the faces' proportions: the lids still meet when the driver's do, but how far a lid lifts is "
        "the eyeball's, which goes with the face's size (persona.plugins.face.warp.retarget; docs/expression.md)")
    neutral: Literal["auto", "clip", "collection"] = Field(
        "auto", description="what the driver's expression is measured from (retargeting: the puppet's target "
        "fiducials are its mean ones plus the driver's offsets from this): 'clip', the paper's, the mean of the "
        "driver's frames, which takes out whatever the driver holds through the clip (a smile, a surprise); "
        "'collection' (not in the paper), the mean of the driver's photo collection, as the puppet's neutral is "
        "its own collection's mean; 'auto', 'collection' where the driver is the puppet (a self-reenactment: the "
        "two means are one, so the targets are the driver's own fiducials) and 'clip' otherwise "
        "(docs/expression.md)")
    neutral_share: float = Field(
        1.0, gt=0, le=1, description="how each face's neutral is taken from its fiducials (retargeting: the "
        "puppet's collection, and the driver's clip or collection as `neutral` says): the mean of this share of "
        "them, those whose shape lies nearest the generic face's after a similarity fit (persona.plugins.face."
        "fiducials.rest_shape). 1, the paper's, is the mean of all; less (not in the paper) leaves out the "
        "expressions furthest from a resting face, so that a puppet built from one clip in which it frowns or "
        "gapes most of the time rests when the driver rests (docs/expression.md)")
    dynamics: DynamicsParams = Field(default_factory=DynamicsParams, description="the driver's per-frame "
                                     "3D flow (ALGORITHMS §9), used by 3D renderers")
    flow: FlowChoice = Field(default_factory=FlowChoice, description="the 2D flow of the per-frame 3D flow "
                             "(reference -> frame, after the landmark guide; 'varref' by default, chosen "
                             "in docs/expression.md)")
    correspondence: CorrespondenceParams = Field(default_factory=CorrespondenceParams, description="the "
                                                 "driver <-> puppet correspondence φ, used by 3D renderers")
    export_every: int = Field(0, ge=0, description="with a 3D renderer, also write B's textured mesh of every "
                              "n-th driver frame (PLY and OBJ + texture) into <output>/meshes/; 0 = none")


BACKENDLESS = {"ingest": IngestParams, "screen": ScreenParams, "align": AlignParams, "motion": MotionParams}


def _resolve(path: str, base: Path) -> str:
    if "://" in path:
        return path
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (base / p).resolve())


def _yaml_path(loc: tuple) -> str:
    return ".".join(str(p) for p in loc)


def _model_at(loc: tuple) -> type[BaseModel] | None:
    """The pydantic model whose field names are valid at ``loc`` (for did-you-mean)."""
    model: type[BaseModel] | None = Workflow
    parts = list(loc)
    while parts and model is not None:
        part = str(parts.pop(0))
        if model is Workflow and part == "stages":  # stages.<kind> is a StageConfig
            if not parts:
                return None
            parts.pop(0)
            model = StageConfig
            continue
        field = model.model_fields.get(part)
        if field is None:
            return None
        args = getattr(field.annotation, "__args__", (field.annotation,))
        model = next((a for a in args if isinstance(a, type) and issubclass(a, BaseModel)), None)
    return model


def _pydantic_errors(exc: ValidationError) -> list[tuple[str, str]]:
    """(yaml path, message) per error; one per path (a union reports once per branch)."""
    out: dict[str, str] = {}
    for err in exc.errors():
        loc = tuple(p for p in err["loc"] if p not in ("str", "list[str]", "VideoRange"))
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            model = _model_at(loc[:-1])
            names = [n for n in (model.model_fields if model else ()) if n != "base_dir"]
            msg = f'unknown key "{loc[-1]}".{did_you_mean(loc[-1], names)}'
        out.setdefault(_yaml_path(loc), msg)
    return list(out.items())


def _check_stages(wf: Workflow, registry: Registry) -> list[tuple[str, str]]:
    errors = []
    kinds = set(registry.kinds()) | set(BACKENDLESS)
    for kind, config in wf.stages.items():
        path = f"stages.{kind}"
        if kind in BACKENDLESS:
            if config.backend is not None:
                errors.append((f"{path}.backend", f'"{kind}" has no backends to choose; remove "backend"'))
            try:
                BACKENDLESS[kind].model_validate(config.params)
            except ValidationError as exc:
                errors += _params_errors(exc, f"{path}.params", BACKENDLESS[kind])
            continue
        if kind not in kinds:
            errors.append((path, f'unknown stage kind "{kind}".{did_you_mean(kind, kinds)} '
                                 f"Known kinds: {', '.join(sorted(kinds))}."))
            continue
        name = config.backend or registry.default(kind)
        if name not in registry.names(kind):
            names = registry.names(kind)
            errors.append((f"{path}.backend", f'unknown {kind} backend "{name}".{did_you_mean(name, names)} '
                                              f"Installed: {', '.join(names)}."))
            continue
        params_model = registry.get(kind, name).Params
        try:
            params_model.model_validate(config.params)
        except ValidationError as exc:
            errors += _params_errors(exc, f"{path}.params", params_model)
    return errors


def _check_people(wf: Workflow) -> list[tuple[str, str]]:
    """The keys each format needs and forbids, people's names, and the people each drive names."""
    errors = []
    if wf.version == 1:
        if wf.puppet is None:
            errors.append(("puppet", "required in a version-1 workflow (or write version: 2 with people and drives)"))
        errors += [(key, f"{key} belongs to version 2: write version: 2, and people and drives instead of puppet "
                         "and driver") for key in ("people", "drives") if getattr(wf, key)]
        return errors
    errors += [(key, f"{key} belongs to version 1: in version 2, name each person under people and say who "
                     "drives whom under drives") for key in ("puppet", "driver") if getattr(wf, key) is not None]
    if not wf.people:
        errors.append(("people", "a version-2 workflow needs people: name: {photos: FOLDER}"))
    errors += [(f"people.{name}", "a person's name is letters, digits, - and _ (it names folders)")
               for name in wf.people if not re.fullmatch(r"[A-Za-z0-9_-]+", name)]
    for i, d in enumerate(wf.drives):
        named = [(f"drives.{i}.puppet", name) for name in d.puppets()] + [(f"drives.{i}.driver", d.driver)]
        errors += [(where, f'no person "{name}" under people.{did_you_mean(name, wf.people)} '
                           f"People: {', '.join(wf.people) or '(none)'}.") for where, name in named
                   if name not in wf.people]
    return errors


def _params_errors(exc: ValidationError, prefix: str, model: type[BaseModel]) -> list[tuple[str, str]]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"])
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = (f'unknown parameter "{loc}".{did_you_mean(loc, model.model_fields)} '
                   f"Parameters: {', '.join(model.model_fields) or '(none)'}.")
        out.append((f"{prefix}.{loc}", msg))
    return out


def _resolve_paths(wf: Workflow, base: Path) -> None:
    wf.store = _resolve(wf.store, base)
    wf.output = _resolve(wf.output, base)
    if wf.cluster.log_directory is not None:
        wf.cluster.log_directory = _resolve(wf.cluster.log_directory, base)
    if wf.cluster.tls is not None:
        for name in ("ca_file", "cert", "key"):
            setattr(wf.cluster.tls, name, _resolve(getattr(wf.cluster.tls, name), base))
    for actor in (wf.puppet, wf.driver, *wf.people.values(), *wf.drives):
        if actor is None:
            continue
        for attr in ("photos", "video"):
            if not hasattr(actor, attr):
                continue
            spec = getattr(actor, attr)
            items = spec if isinstance(spec, list) else [spec]
            resolved = [_resolve(s, base) if isinstance(s, str) else s for s in items]
            for s in resolved:
                if isinstance(s, VideoRange):
                    s.video = _resolve(s.video, base)
            setattr(actor, attr, resolved if isinstance(spec, list) else resolved[0])


def set_override(data: dict, assignment: str) -> None:
    """Apply ``key.sub=value`` (value parsed as YAML) to raw workflow data."""
    if "=" not in assignment:
        raise WorkflowError("--set", [(assignment, "expected key=value, e.g. cluster.workers=2")])
    key, value = assignment.split("=", 1)
    parts = key.strip().split(".")
    node = data
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise WorkflowError("--set", [(key, f'"{part}" is not a mapping')])
    node[parts[-1]] = yaml.safe_load(value)


#: params of a stage that became a stage kind of their own, still read where they were:
#: (stage, key) -> the kind whose ``stages.<kind>.params`` they are now
MOVED = {("motion", "transfer"): "transfer"}


def _moved(data: dict, source: str) -> dict:
    """``data`` with each :data:`MOVED` key given where it was (``stages.motion.params.transfer``) moved to
    its kind's params (``stages.transfer.params``); given in both places, it is an error."""
    stages = data.get("stages")
    if not isinstance(stages, dict):
        return data
    stages = dict(stages)
    for (stage, key), kind in MOVED.items():
        config = stages.get(stage)
        params = config.get("params") if isinstance(config, dict) else None
        if not isinstance(params, dict) or key not in params:
            continue
        mine = stages.get(kind) or {}
        if not isinstance(mine, dict) or mine.get("params"):
            raise WorkflowError(source, [(f"stages.{stage}.params.{key}", f"also given as stages.{kind}.params: "
                                                                          "give it once, there")])
        stages[stage] = {**config, "params": {k: v for k, v in params.items() if k != key}}
        stages[kind] = {**mine, "params": params[key]}
    return {**data, "stages": stages}


def parse_workflow(data: Any, *, source: str = "<workflow>", base_dir: str | Path = ".",
                   registry: Registry | None = None) -> Workflow:
    """Validate raw YAML data into a :class:`Workflow`, or raise WorkflowError with every error."""
    registry = registry or default_registry()
    if not isinstance(data, dict):
        raise WorkflowError(source, [("", f"a workflow is a YAML mapping, got {type(data).__name__}")])
    data = _moved(data, source)
    try:
        wf = Workflow.model_validate({**data, "base_dir": str(base_dir)})
    except ValidationError as exc:
        errors = _pydantic_errors(exc)
        # stage checks still run on what parsed, so every error is reported at once
        stages = data.get("stages")
        if isinstance(stages, dict):
            try:
                partial = Workflow.model_construct(stages={k: StageConfig.model_validate(v or {})
                                                           for k, v in stages.items()})
                errors += _check_stages(partial, registry)
            except ValidationError:
                pass
        raise WorkflowError(source, errors) from None
    errors = _check_stages(wf, registry) + _check_people(wf)
    if errors:
        raise WorkflowError(source, errors)
    _resolve_paths(wf, Path(base_dir))
    if wf.cluster.tls is not None:
        missing = [(f"cluster.tls.{name}", f"{path} is not a file: give the PEM file's path (relative to the "
                    "workflow's folder)") for name, path in wf.cluster.tls.model_dump().items() if not Path(path).is_file()]
        if missing:
            raise WorkflowError(source, missing)
    storage.configure(wf.storage_options.fsspec())  # this process's; the runner's Dask workers get them too
    return wf


def load_workflow(path: str | Path, overrides: list[str] = (), registry: Registry | None = None) -> Workflow:
    """Read, override and validate a workflow file."""
    path = Path(path)
    if not path.is_file():
        raise WorkflowError(str(path), [("", "no such file: give the path of a workflow YAML file")])
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise WorkflowError(str(path), [("", f"invalid YAML at {where}{problem}")]) from None
    except UnicodeDecodeError:
        raise WorkflowError(str(path), [("", "not a text file: a workflow is a YAML text file")]) from None
    if data is None:
        raise WorkflowError(str(path), [("", "the file is empty: see workflows/demo.yaml for an example")])
    if isinstance(data, dict):
        for assignment in overrides:
            set_override(data, assignment)
    return parse_workflow(data, source=str(path), base_dir=path.resolve().parent, registry=registry)


def json_schema() -> dict:
    """The workflow's JSON schema, with the params of the stages that have no backend choice
    (ingest, align, motion) under ``x-stage-params``; each backend's params are in
    ``persona plugins --json``."""
    schema = Workflow.model_json_schema()
    schema["x-stage-params"] = {kind: model.model_json_schema() for kind, model in BACKENDLESS.items()}
    return schema



