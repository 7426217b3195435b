"""The three layers, one direction (README, "Layout"): ``dag/`` may use ``plugins/`` and
``stores/``; ``plugins/`` (the maths, pure NumPy) uses neither ``dag/`` nor ``stores/`` nor the
dataflow's libraries; ``stores/`` (layout and media) uses neither ``dag/`` nor ``plugins/``.

Read from the source with :mod:`ast`, every import anywhere in a file (inside functions too),
relative imports resolved against the file's package."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"dag": "persona.dag", "plugins": "persona.plugins", "stores": "persona.stores"}

#: what each layer must not import: other layers, and for the maths the dataflow's libraries
FORBIDDEN = {
    "plugins": ("persona.dag", "persona.stores", "dask", "distributed", "zarr"),
    "stores": ("persona.dag", "persona.plugins"),
}


def imports(path: Path, layer: str) -> list[tuple[int, str]]:
    """(line, module) of every import in the file ``path`` of ``layer``."""
    package = ".".join([PACKAGES[layer], *path.relative_to(ROOT / layer).parent.parts])
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # from ..x import y: up level-1 packages from this file's package
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module
            found.append((node.lineno, module))
    return found


def offences(layer: str) -> list[str]:
    out = []
    for path in sorted((ROOT / layer).rglob("*.py")):
        for line, module in imports(path, layer):
            if any(module == bad or module.startswith(bad + ".") for bad in FORBIDDEN[layer]):
                out.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    return out


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_a_layer_imports_nothing_above_or_beside_it(layer):
    assert offences(layer) == []


def test_the_check_sees_relative_and_nested_imports(tmp_path, monkeypatch):
    """The check itself can fail: a relative import of dag/ inside a function of a plugin, and a
    plain ``import zarr``, are both found."""
    fake = tmp_path / "plugins" / "face"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text("import numpy\n\ndef f():\n    from ...dag import runner\n    import zarr\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert offences("plugins") == ["plugins/face/bad.py:4 imports persona.dag", "plugins/face/bad.py:5 imports zarr"]
