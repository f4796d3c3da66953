"""The package's layout: layers that import only downwards, small modules, no private reach."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torch_api"
MAX_LINES = 400

# the layers, bottom first: a module may import its own layer's and those below; ``runs`` lies
# beside them and imports only the base (collection uses its process lifetime, the loop its
# store). torch_api/__init__.py, the public names, imports from all.
LAYERS = {
    "base": 0,  # torch_api/*.py: streams, _checks, _logging
    "data": 1,
    "runs": 1,
    "core": 2,
    "policies": 3,
    "collection": 4,
    "loop": 5,
    "experiment": 6,
}


def _layer(path: Path) -> str:
    parts = path.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 else "base"


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
    return {n for n in names if n.startswith("torch_api.")}


MODULES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize(
    "path", [p for p in MODULES if p != PACKAGE / "__init__.py"], ids=lambda p: p.name
)
def test_a_module_imports_only_its_layer_and_those_below(path):
    mine = LAYERS[_layer(path)]
    upwards = []
    for name in _imports(path):
        parts = name.split(".")
        layer = parts[1] if len(parts) > 2 or (PACKAGE / parts[1]).is_dir() else "base"
        if LAYERS.get(layer, 0) > mine:
            upwards.append(name)
    assert not upwards, f"{path.relative_to(ROOT)} imports upwards: {sorted(upwards)}"


def test_every_module_is_at_most_400_lines():
    files = [*MODULES, *sorted((ROOT / "benchmarks").glob("*.py"))]
    files += sorted((ROOT / "examples").glob("*.py")) + sorted((ROOT / "envs").rglob("*.py"))
    files += sorted((ROOT / "counter_rng").rglob("*.py"))
    long = {
        str(p.relative_to(ROOT)): n
        for p in files
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long, long


# ``name._attr`` on anything but self or cls; NamedTuple's public ``_replace``/``_asdict`` and
# module paths (``torch_api._checks``) are not private state
_REACH = re.compile(
    r"\b(?!self\b|cls\b)([a-z_][a-z0-9_]*)\._(?!replace\b|asdict\b|fields\b)[a-z]\w*"
)
# a copy of self, made by its own class, set up by that class (a policy's new streams)
_ALLOWED = {("torch_api/policies/base.py", "other._streams")}


def test_no_module_reaches_into_another_objects_private_attributes():
    hits = []
    for path in MODULES:
        rel = str(path.relative_to(ROOT))
        for i, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if code.lstrip().startswith(("from ", "import ")):
                continue
            for match in _REACH.finditer(code):
                if match.group(1) == "torch_api" or (rel, match.group(0)) in _ALLOWED:
                    continue
                hits.append(f"{rel}:{i}: {match.group(0)}")
    assert not hits, "\n".join(hits)


def test_no_class_of_the_loop_is_a_mixin():
    from torch_api.loop.iteration import ActivePolicyIteration

    assert ActivePolicyIteration.__bases__ == (object,)
