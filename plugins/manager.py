"""Find, load and register every backend (built-in or third-party) through pluggy.

Built-ins are ordinary plugins listed in ``DEFAULT_PLUGINS`` and go through the same
``persona_register_backends`` hook as third-party plugins, which are found through the
``persona`` entry-point group. Set ``PERSONA_PLUGINS`` to a comma-separated list of
entry-point names to load only those, or to an empty string to load none (the tests do
so, so that whatever happens to be installed cannot change their results).
"""

from __future__ import annotations

import difflib
import importlib
import importlib.metadata
import logging
import os
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import pluggy
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from . import hookspecs
from .base import Backend

log = logging.getLogger(__name__)

DEFAULT_PLUGINS = (
    "persona.plugins.builtin.landmarks",
    "persona.plugins.builtin.pose",
    "persona.plugins.builtin.frontalize",
    "persona.plugins.builtin.render",
    "persona.plugins.builtin.render3d",
    "persona.plugins.builtin.evaluate",
    "persona.plugins.builtin.flow",
    "persona.plugins.builtin.shape",
    "persona.plugins.builtin.integrate",
    "persona.plugins.builtin.denoise",
    "persona.plugins.builtin.texture",
    "persona.plugins.builtin.composite",
    "persona.plugins.builtin.mouth",
    "persona.plugins.builtin.transfer",
)

ENTRY_POINT_GROUP = "persona"


class PluginError(Exception):
    """A backend or plugin is missing, misnamed or malformed."""


class UnknownBackend(PluginError, KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def did_you_mean(word: str, choices) -> str:
    """' Did you mean "x"?' for the closest choice, or ''."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f' Did you mean "{close[0]}"?' if close else ""


@dataclass(frozen=True)
class BackendInfo:
    cls: type[Backend]
    distribution: str  # "persona 0.1.0" or the third-party distribution that supplied it

    def describe(self) -> dict:
        c = self.cls
        return {
            "kind": c.kind,
            "name": c.name,
            "description": c.description,
            "version": c.version,
            "default": bool(c.default),
            "distribution": self.distribution,
            "params": c.Params.model_json_schema(),
        }


class Registry:
    """Backends by (kind, name), with checks on what gets registered."""

    def __init__(self):
        self._backends: dict[tuple[str, str], BackendInfo] = {}
        self.broken: dict[str, str] = {}  # plugin name -> why it could not load

    def register(self, cls: type[Backend], *, distribution: str) -> None:
        if not (isinstance(cls, type) and issubclass(cls, Backend)):
            raise PluginError(f"{distribution}: register() wants a Backend subclass, got {cls!r}")
        for attr in ("name", "kind", "description"):
            if not isinstance(getattr(cls, attr, None), str) or not getattr(cls, attr):
                raise PluginError(f"{distribution}: backend {cls.__name__} has no {attr!r} string")
        if not (isinstance(cls.Params, type) and issubclass(cls.Params, BaseModel)):
            raise PluginError(f"{distribution}: {cls.__name__}.Params must be a pydantic model")
        if cls.Params.model_config.get("extra") != "forbid":
            raise PluginError(
                f"{distribution}: {cls.__name__}.Params must forbid unknown keys "
                "(subclass persona.plugins.base.Params)"
            )
        key = (cls.kind, cls.name)
        if key in self._backends:
            other = self._backends[key]
            raise PluginError(
                f"{distribution}: a {cls.kind} backend named {cls.name!r} is already "
                f"registered by {other.distribution}"
            )
        self._backends[key] = BackendInfo(cls, distribution)

    def kinds(self) -> list[str]:
        return sorted({k for k, _ in self._backends})

    def names(self, kind: str) -> list[str]:
        return sorted(n for k, n in self._backends if k == kind)

    def info(self, kind: str, name: str) -> BackendInfo:
        if kind not in self.kinds():
            raise UnknownBackend(
                f'unknown kind "{kind}".{did_you_mean(kind, self.kinds())} '
                f"Known kinds: {', '.join(self.kinds())}."
            )
        try:
            return self._backends[(kind, name)]
        except KeyError:
            names = self.names(kind)
            raise UnknownBackend(
                f'unknown {kind} backend "{name}".{did_you_mean(name, names)} '
                f"Installed {kind} backends: {', '.join(names)} (see `persona plugins`)."
            ) from None

    def get(self, kind: str, name: str) -> type[Backend]:
        return self.info(kind, name).cls

    def default(self, kind: str) -> str:
        names = self.names(kind)
        defaults = [n for n in names if self._backends[(kind, n)].cls.default]
        return (defaults or names)[0]

    def all(self) -> list[BackendInfo]:
        return [self._backends[k] for k in sorted(self._backends)]


def _builtin_distribution() -> str:
    try:
        return f"persona {importlib.metadata.version('persona')}"
    except importlib.metadata.PackageNotFoundError:
        return "persona (not installed)"


def selected() -> str | None:
    """This process's choice of entry-point plugins: ``PERSONA_PLUGINS`` (None: all of them)."""
    return os.environ.get("PERSONA_PLUGINS")


def select(choice: str | None) -> None:
    """Load the entry-point plugins ``choice`` (as :func:`selected` gives it) from now on in this process,
    the registry rebuilt on its next use: a run's Dask workers load the plugins the run's own process
    loads, whatever their machine's environment says."""
    if choice == selected():
        return
    if choice is None:
        os.environ.pop("PERSONA_PLUGINS", None)
    else:
        os.environ["PERSONA_PLUGINS"] = choice
    default_registry.cache_clear()


def _entry_points() -> list[importlib.metadata.EntryPoint]:
    eps = list(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))
    allow = selected()
    if allow is None:
        return eps
    wanted = {n.strip() for n in allow.split(",") if n.strip()}
    return [ep for ep in eps if ep.name in wanted]


def get_plugin_manager(extra_plugins=()) -> tuple[pluggy.PluginManager, Registry]:
    """A plugin manager with the built-ins, the entry-point plugins and ``extra_plugins``,
    and the registry of every backend they registered."""
    pm = pluggy.PluginManager("persona")
    pm.add_hookspecs(hookspecs)
    registry = Registry()
    sources: dict[str, str] = {}
    builtin = _builtin_distribution()
    for module_name in DEFAULT_PLUGINS:
        pm.register(importlib.import_module(module_name), name=module_name)
        sources[module_name] = builtin
    for ep in _entry_points():
        dist = f"{ep.dist.name} {ep.dist.version}" if ep.dist else ep.value
        try:
            pm.register(ep.load(), name=ep.name)
        except Exception as exc:  # a broken third-party plugin is reported, not fatal
            registry.broken[ep.name] = f"{type(exc).__name__}: {exc}"
            log.warning("plugin %s (%s) failed to load: %s", ep.name, dist, exc)
            continue
        sources[ep.name] = dist
    for plugin in extra_plugins:
        name = pm.register(plugin)
        sources[name] = getattr(plugin, "__name__", name)
    pm.check_pending()
    for impl in pm.hook.persona_register_backends.get_hookimpls():
        distribution = sources.get(impl.plugin_name, impl.plugin_name)
        impl.function(register=lambda cls, d=distribution: registry.register(cls, distribution=d))
    return pm, registry


@lru_cache(maxsize=1)
def default_registry() -> Registry:
    """The registry of the installed plugins (cached; for validation and listing)."""
    return get_plugin_manager()[1]


class FlowChoice(BaseModel):
    """A flow backend and its parameters, for a step that is not the workflow's ``flow`` stage
    (the collection flow): the driver's dynamics, the correspondence, texture synthesis."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    backend: str = Field("varref", description="the flow backend's name (`persona plugins` lists them)")
    params: dict[str, Any] = Field(default_factory=dict, validate_default=True,
                                   description="the flow backend's parameters (its defaults where left out)")

    @field_validator("backend")
    @classmethod
    def _backend(cls, name: str) -> str:
        try:
            default_registry().get("flow", name)
        except UnknownBackend as e:  # a KeyError; pydantic reports ValueErrors
            raise ValueError(str(e)) from None
        return name

    @field_validator("params")
    @classmethod
    def _params(cls, params: dict, info: ValidationInfo) -> dict:
        if "backend" not in info.data:  # the name was invalid: that error says enough
            return params
        try:
            return default_registry().get("flow", info.data["backend"]).Params.model_validate(params).model_dump(
                mode="json")
        except ValidationError as e:
            errors = (f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
            raise ValueError("; ".join(errors)) from None

    def build(self):
        """The flow backend itself."""
        return default_registry().get("flow", self.backend)(self.params)
