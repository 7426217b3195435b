"""The ``persona`` package: Persona's Python API (:mod:`persona.dag.api`) and its three layers.

The repository's top level holds the layers themselves (dag/, plugins/, stores/), so this package has no
folder of its own there: pyproject.toml maps ``persona`` to this folder (dag/_persona/) and
``persona.dag``, ``persona.plugins`` and ``persona.stores`` to theirs. Nothing is imported until it is
used: ``import persona.plugins.kinds`` on a Dask worker stays as light as it was, and ``persona.run``
loads the API on first use.
"""

__all__ = ["open", "run", "workflow", "Run", "Person", "Video", "Drive"]


def __getattr__(name: str):
    if name in __all__:
        from persona.dag import api

        return getattr(api, name)
    raise AttributeError(f"module 'persona' has no attribute {name!r}; Persona's API: {', '.join(__all__)}")


def __dir__() -> list[str]:
    return sorted([*__all__, "dag", "plugins", "stores"])
