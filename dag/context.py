"""What a stage's ``run`` function, and the parts of a run beside the runner, are given: the run as
:class:`RunContext`. The runner (:class:`persona.dag.runner.Runner`) is one; the stage modules read this
type rather than import the runner, which imports them.
"""

from __future__ import annotations

from typing import Protocol

import zarr

from persona.stores.layout import Collection
from persona.stores.provenance import Provenance

from .executor import Executor
from .progress import StageTimer
from .stages import PhotoStage
from .tasks import Tasks
from .workflow import Workflow


class RunContext(Protocol):
    #: the workflow being run
    wf: Workflow
    #: its store, open for writing
    root: zarr.Group
    #: Persona's version, recorded in every provenance
    version: str
    executor: Executor
    #: the run's tasks with hooks and progress (:class:`persona.dag.tasks.Tasks`)
    tasks: Tasks
    timer: StageTimer
    #: why a collection has no 3D shape in this run
    shape_problems: dict

    def ingest_params(self) -> dict: ...

    def align_params(self) -> dict: ...

    def motion_params(self) -> dict: ...

    def render_params(self): ...

    def uses_mesh(self) -> bool: ...

    def steps(self, coll: Collection) -> list[tuple[str, str, dict]]: ...

    def prepare_stage(self, coll: Collection, stage: PhotoStage, inputs: dict[str, str],
                      choice: tuple[str, dict] | None = None, key_params: dict | None = None) -> Provenance: ...

    def build_collection(self, plan, sources: list, report: dict) -> dict: ...

    def drive(self, plan) -> dict: ...

    def evaluate(self, cast=..., progress=...) -> dict: ...
