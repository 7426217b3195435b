"""The three layers, one direction (README, "Layout"): ``dag/`` may use ``plugins/`` and
``stores/``; ``plugins/`` (the maths, pure NumPy) uses neither ``dag/`` nor ``stores/`` nor the
dataflow's libraries; ``stores/`` (layout and media) uses neither ``dag/`` nor ``plugins/``. And no two
modules import each other, however indirectly: each can be read, and changed, after what it uses.

Read from the source with :mod:`ast`, every import anywhere in a file (inside functions too),
relative imports resolved against the file's package. And no class is longer than ``MAX_CLASS_LINES``: a
class that grows past it is split, its pieces moved into functions or helpers of its own module."""

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


def imports(path: Path, layer: str, names: bool = False) -> list[tuple[int, str]]:
    """(line, module) of every import in the file ``path`` of ``layer``; with ``names``, each name a
    ``from`` import takes as well (``from . import stages`` gives ``persona.dag`` and ``persona.dag.stages``)."""
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
            if names:
                found += [(node.lineno, f"{module}.{alias.name}") for alias in node.names]
    return found


def offences(layer: str) -> list[str]:
    out = []
    for path in sorted((ROOT / layer).rglob("*.py")):
        for line, module in imports(path, layer):
            if any(module == bad or module.startswith(bad + ".") for bad in FORBIDDEN[layer]):
                out.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    return out


def cycles() -> list[str]:
    """Every import cycle among the project's modules (packages' ``__init__`` aside), as "a -> b -> a"."""
    files = {}
    for layer, package in PACKAGES.items():
        for path in sorted((ROOT / layer).rglob("*.py")):
            if path.name != "__init__.py":
                files[".".join([package, *path.relative_to(ROOT / layer).with_suffix("").parts])] = (path, layer)
    uses = {name: sorted({m for _, m in imports(path, layer, names=True) if m in files and m != name})
            for name, (path, layer) in files.items()}
    found, done = [], set()

    def visit(name, trail):  # depth first; a module met again on the trail closes a cycle
        if name in trail:
            found.append(" -> ".join(trail[trail.index(name):] + [name]))
        elif name not in done:
            for other in uses[name]:
                visit(other, trail + [name])
            done.add(name)
    for name in sorted(uses):
        visit(name, [])
    return found


#: the most lines a class of dag/, plugins/ or stores/ may take (docstring and nested classes included)
MAX_CLASS_LINES = 200


def classes(lines: int) -> list[str]:
    """Every class of the three layers longer than ``lines`` lines, as "path:line Name (n lines)"."""
    out = []
    for layer in PACKAGES:
        for path in sorted((ROOT / layer).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > lines:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} "
                               f"({node.end_lineno - node.lineno + 1} lines)")
    return out


def test_no_class_is_longer_than_the_limit():
    assert classes(MAX_CLASS_LINES) == []


def test_the_class_check_sees_a_long_class(tmp_path, monkeypatch):
    fake = tmp_path / "stores"
    fake.mkdir()
    (fake / "big.py").write_text("class Big:\n" + "    x = 1\n" * 200)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert classes(MAX_CLASS_LINES) == ["stores/big.py:1 Big (201 lines)"]


def test_no_two_modules_import_each_other():
    assert cycles() == []


def test_the_cycle_check_sees_a_cycle_through_a_function(tmp_path, monkeypatch):
    fake = tmp_path / "dag"
    fake.mkdir()
    (fake / "a.py").write_text("from . import b\n")
    (fake / "b.py").write_text("def f():\n    from .c import g\n")
    (fake / "c.py").write_text("from persona.dag.a import x\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert cycles() == ["persona.dag.a -> persona.dag.b -> persona.dag.c -> persona.dag.a"]


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
