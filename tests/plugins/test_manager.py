import json

import pytest

from persona.plugins.base import Backend, Params
from persona.plugins.hookspecs import hookimpl
from persona.plugins.kinds import LandmarkBackend
from persona.plugins.manager import (PluginError, Registry, UnknownBackend, default_registry,
                                     get_plugin_manager)


def test_builtins_registered_with_defaults():
    registry = default_registry()
    for kind in ("landmarks", "pose", "frontalize"):
        assert registry.names(kind), kind
        assert registry.default(kind) in registry.names(kind)
    assert registry.default("landmarks") == "dlib"
    assert "sidecar" in registry.names("landmarks")


def test_unknown_backend_suggests_the_nearest_name():
    with pytest.raises(UnknownBackend, match='Did you mean "dlib"'):
        default_registry().get("landmarks", "dlb")
    with pytest.raises(UnknownBackend, match='Did you mean "landmarks"'):
        default_registry().get("landmark", "dlib")


class ThirdPartyLandmarks(LandmarkBackend):
    name = "centre"
    description = "a third party's landmarks"

    class Params(Params):
        size: float = 1.0


class ThirdPartyPlugin:
    @hookimpl
    def persona_register_backends(self, register):
        register(ThirdPartyLandmarks)


def test_third_party_plugin_registers_like_builtins():
    pm, registry = get_plugin_manager(extra_plugins=[ThirdPartyPlugin()])
    assert registry.get("landmarks", "centre") is ThirdPartyLandmarks
    described = [b.describe() for b in registry.all() if b.cls is ThirdPartyLandmarks][0]
    assert described["params"]["properties"]["size"]["default"] == 1.0
    assert described["distribution"]
    json.dumps(described)  # the CLI prints these as JSON


def test_registry_refuses_malformed_and_duplicate_backends():
    registry = Registry()

    class NoName(Backend):
        kind = "landmarks"
        description = "x"

    with pytest.raises(PluginError, match="no 'name'"):
        registry.register(NoName, distribution="test")

    class LooseParams(Backend):
        name, kind, description = "loose", "landmarks", "x"

        from pydantic import BaseModel as Params  # noqa: N814 - allows unknown keys

    with pytest.raises(PluginError, match="forbid unknown keys"):
        registry.register(LooseParams, distribution="test")
    registry.register(ThirdPartyLandmarks, distribution="a")
    with pytest.raises(PluginError, match="already registered by a"):
        registry.register(ThirdPartyLandmarks, distribution="b")


def test_params_are_strict():
    from pydantic import ValidationError

    backend = default_registry().get("landmarks", "dlib")
    with pytest.raises(ValidationError):
        backend({"selct": "largest"})
    with pytest.raises(ValidationError):
        backend({"select": "leftmost"})
    assert backend({"select": "largest"}).params.select == "largest"


def test_every_hookspec_is_called_by_the_runner():
    """Like datasette's test: a hook nobody calls is a broken promise."""
    import inspect

    from persona.dag import tasks
    from persona.plugins import hookspecs

    source = inspect.getsource(tasks)
    specs = [n for n, f in vars(hookspecs).items() if n.startswith("persona_") and callable(f)]
    assert specs
    for name in specs:
        assert f"hook.{name}(" in source or name == "persona_register_backends", name
