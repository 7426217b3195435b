"""What every backend is: a class with a name, a kind, a description and strict params.

Backends are pure algorithms on NumPy arrays. They never see Dask, Zarr or a file
path; the DAG reads their inputs from the store and writes their outputs back.
A backend that cannot process one photo raises :class:`Rejected` with a short,
specific reason: the photo is recorded as rejected and the run goes on.
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import BaseModel, ConfigDict


class Params(BaseModel):
    """Base of every backend's parameters: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Rejected(Exception):
    """One input item (photo or frame) cannot be processed; ``reason`` says why."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Backend:
    """Base class of all backends.

    Subclasses set the class attributes and implement the method that their
    kind's contract names (see :mod:`persona.plugins.kinds`).
    """

    name: ClassVar[str]
    kind: ClassVar[str]
    description: ClassVar[str]
    version: ClassVar[str] = "1"
    #: the backend a workflow gets when it names none for this kind
    default: ClassVar[bool] = False
    #: the backend name cache keys record, when not ``name``: "-" for the built-in backend of a stage that
    #: had no backend choice before its kind existed (the composite, the light, the mouth, the transfer), so
    #: that what it made before stays valid
    key_name: ClassVar[str | None] = None

    class Params(Params):
        pass

    def __init__(self, params: Params | dict | None = None):
        if isinstance(params, self.Params):
            self.params = params
        else:
            self.params = self.Params.model_validate(params or {})

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})"
