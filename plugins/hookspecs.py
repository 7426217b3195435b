"""The contract between Persona and its plugins (pluggy hook specifications).

A plugin is any module or object with functions marked ``@hookimpl`` whose names
match the specs below. Built-in backends and third-party packages register the
same way; third parties announce their module in the ``persona`` entry-point
group of their ``pyproject.toml``::

    [project.entry-points.persona]
    my_flow = "my_package.persona_plugin"

The lifecycle hooks (``persona_before_stage`` and the others) come from the process that runs the
workflow. A version-2 workflow builds several people at once (``cluster.builds``), each in a
thread of its own, so these hooks may be called from several threads at the same time, for
different collections; a plugin that keeps state across calls should key it by collection (or
take a lock).
"""

import pluggy

hookspec = pluggy.HookspecMarker("persona")
hookimpl = pluggy.HookimplMarker("persona")


@hookspec
def persona_register_backends(register):
    """Register backend classes by calling ``register(BackendClass)`` once per class.

    A backend class subclasses :class:`persona.plugins.base.Backend` and sets
    ``name``, ``kind``, ``description`` and a strict pydantic ``Params`` model.
    """


@hookspec
def persona_before_stage(stage, collection, info):
    """Called before a stage runs on one collection (e.g. ``"puppet"``).

    ``info``: for a per-photo or per-frame stage, a dict with ``backend``, ``params`` and ``n_items``; for a
    collection-level step (shape, texture, motion, ...: one step, not items), an empty dict.
    """


@hookspec
def persona_after_stage(stage, collection, summary):
    """Called after a stage finished on one collection.

    ``summary`` holds ``seconds``, and for a per-photo or per-frame stage also ``n_done``, ``n_skipped``,
    ``n_ok`` and ``n_rejected``.
    """


@hookspec
def persona_stage_error(stage, collection, error):
    """Called when a stage fails with an exception (the run stops after this)."""
