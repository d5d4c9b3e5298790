"""One room per concept: no module reaches into another module's underscore names.

A leading underscore marks what a module or class keeps to itself; using it from
outside ties the two together behind the interface's back. The check reads the source
with `ast`: ``from hyper.x import _y`` and ``X._y`` for any X but ``self`` and ``cls``
(an imported module, another module's object, a component held in an attribute) are
violations. Dunder names (``__name__``, ``__dict__``) are Python's, not a module's.
"""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "hyper"


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def violations(source: str, filename: str = "<source>") -> list[str]:
    """``file:line: what`` for each use of another module's or object's underscore name."""
    tree = ast.parse(source, filename)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").split(".")[0] == "hyper"):
            for alias in node.names:
                if _private(alias.name):
                    found.append(f"{filename}:{node.lineno}: from {'.' * node.level}{node.module or ''} "
                                 f"import {alias.name}")
        elif isinstance(node, ast.Attribute) and _private(node.attr):
            owner = node.value
            if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
                continue
            if isinstance(owner, ast.Call) and isinstance(owner.func, ast.Name) and owner.func.id == "super":
                continue  # the class's own implementation, one level up
            found.append(f"{filename}:{node.lineno}: {ast.unparse(node)}")
    return found


@pytest.mark.parametrize("source", [
    "from hyper.bench.growth import _run_worker",
    "from .growth import _plt",
    "from hyper.bench import growth as g\ng._run_worker({}, 1, 1.0)",
    "import hyper.mechanics\nhyper.mechanics._REASONS",
    "def f(problem):\n    return problem._K",
    "class A:\n    def f(self):\n        return self.problem._nowned",
])
def test_the_check_sees_underscore_names_used_from_outside(source):
    assert len(violations(source)) == 1


@pytest.mark.parametrize("source", [
    "class A:\n    def f(self):\n        return self._K",
    "class A:\n    @classmethod\n    def f(cls):\n        return cls._table",
    "class A(B):\n    def f(self):\n        return super()._setup()",
    "def f(x):\n    return x.__class__.__name__",
    "from hyper.mechanics import MechanicsProblem",
])
def test_the_check_lets_a_class_use_its_own_names(source):
    assert violations(source) == []


def test_no_module_uses_another_modules_underscore_names():
    found = [v for path in sorted(SRC.rglob("*.py"))
             for v in violations(path.read_text(), str(path.relative_to(SRC.parent)))]
    assert found == [], "underscore names used outside their module or class:\n" + "\n".join(found)
