"""How a run fails as a whole. Its own module so that the runner and the batch cluster it starts
(:mod:`.batch`) both raise them without importing each other."""

from __future__ import annotations

from persona.stores.errors import PersonaError


class RunError(PersonaError, RuntimeError):
    """A run could not finish; the message says how to resume or fix it."""


class ClusterLost(RunError):
    """The run's Dask scheduler, or every one of its workers, is gone: no person, video or drive can go on."""
