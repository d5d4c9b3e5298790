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


# The standard library's own documented names with an underscore: not another module's
# internals. os._exit: an exit without unwinding (hyper.core.term's TERM handler).
STDLIB_UNDERSCORE_NAMES = {"os._exit"}


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
            if ast.unparse(node) in STDLIB_UNDERSCORE_NAMES:
                continue
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


# ---------------------------------------------------------------------------- layers

# Lowest first: a module imports from its own layer or from those before it, never above.
# The top-level modules hyper/JOB.py are the `python -m hyper.JOB` shims, above everything.
LAYERS = ("core", "model", "fem", "runs", "analysis", "commands")
SHIM = len(LAYERS)

# The third-party modules a function may import inside itself, and why: each is heavy to
# import (seconds of MPI, PETSc and JIT set-up, or a large library) and needed by a few
# paths only, so `hyper JOB --help`, the signaling-only jobs and the fast model start
# without them. Everything else (hyper's own modules, the standard library, numpy) is
# imported at the top of its module.
HEAVY = {
    "dolfinx": "DOLFINx loads MPI, PETSc and the JIT (seconds); the signaling-only jobs never need it",
    "dolfinx_solver": "what DOLFINx needs before it (see dolfinx)",
    "petsc4py": "PETSc initialisation (see dolfinx)",
    "basix": "the finite-element tables, with DOLFINx (see dolfinx)",
    "ufl": "the form language, with DOLFINx (see dolfinx)",
    "matplotlib": "figures only: a large import, and its backend is chosen before pyplot is first imported",
    "mpl_toolkits": "3D figures only (see matplotlib)",
    "gmsh": "meshing a surface only: a large native library",
    "meshio": "reading Gmsh and STL files only",
    "h5py": "HDF5 files only; the signaling kernels and the parsers never touch them",
    "scipy": "special solvers (ODE reference, k-d trees, sparse graphs) on a few paths only",
    "SALib": "the Sobol sampler and analysis only",
    "cffi": "compiling the C signaling kernel, only when it is asked for",
    "mpi4py": "MPI initialisation, only where a job needs a communicator",
    "nibabel": "reading NIfTI DTI images (fibres from data, hyper.fem.fiberread) only",
    "emcee": "the ensemble sampler of `hyper calibrate --method bayes` only; least squares and the grid never need it",
}


def layer(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1:
        return -1  # hyper/__init__.py: the version, nothing else
    return LAYERS.index(parts[1]) if parts[1] in LAYERS else SHIM


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(SRC.rglob("*.py"))}


def imports(path: Path) -> list[tuple[str, int, bool]]:
    """(imported hyper module, line, inside a function or class) for each hyper import of
    ``path``, at module level, under TYPE_CHECKING or inside functions."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    this = module_name(path)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = this.split(".") if path.name == "__init__.py" else this.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] != "hyper":
                continue
            for alias in node.names:
                name = f"{module}.{alias.name}"
                found.append((name if name in MODULES else module, node.lineno, id(node) not in top))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "hyper":
                    found.append((alias.name, node.lineno, id(node) not in top))
    return found


def test_every_module_sits_in_a_layer():
    loose = [m for m in MODULES if layer(m) == SHIM and not (m.count(".") == 1)]
    assert loose == []
    shims = [m for m in MODULES if layer(m) == SHIM]
    for name in shims:
        text = MODULES[name].read_text()
        job = f"from hyper.commands.{name.split('.')[1]} import main"
        assert job in text, f"{name} is not a thin shim"
        assert len(text.splitlines()) <= 11, f"{name} is more than a shim"
        # the early TERM handler (hyper.core.term) before the job's imports: see test_term.py
        assert "from hyper.core import term\n\nterm.install()" in text.split(job)[0], (
            f"{name} does not install hyper.core.term before it imports its job")


def test_imports_point_down_the_layers():
    found = []
    for name, path in MODULES.items():
        for target, line, _ in imports(path):
            if layer(target) > layer(name):
                found.append(f"{path.relative_to(SRC.parent)}:{line}: {name} ({LAYERS[layer(name)]}) imports "
                             f"{target} ({LAYERS[layer(target)] if layer(target) < SHIM else 'a shim'})")
    assert found == [], "imports from a lower layer to a higher one:\n" + "\n".join(found)


def test_no_library_module_imports_the_command_layer():
    found = [f"{path.relative_to(SRC.parent)}:{line}: {target}" for name, path in MODULES.items()
             if layer(name) < LAYERS.index("commands") for target, line, _ in imports(path)
             if target.startswith("hyper.commands") or layer(target) == SHIM]
    assert found == []


def third_party(path: Path) -> set[str]:
    """The top-level names of the third-party packages ``path`` imports at module level."""
    tree = ast.parse(path.read_text())
    names = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names - {"hyper"}


def heavy_modules() -> dict[str, str]:
    """hyper's modules whose import loads a `HEAVY` package, themselves or through the
    modules they import at module level: {module: the heavy package}."""
    top = {name: {t for t, _, inner in imports(path) if not inner and t in MODULES and t != name}
           for name, path in MODULES.items()}
    heavy = {}
    for name, path in MODULES.items():
        found = sorted(third_party(path) & set(HEAVY))
        if found:
            heavy[name] = found[0]
    changed = True
    while changed:
        changed = False
        for name, targets in top.items():
            if name not in heavy:
                reached = [heavy[t] for t in sorted(targets) if t in heavy]
                if reached:
                    heavy[name] = reached[0]
                    changed = True
    return heavy


def test_hyper_imports_inside_functions_only_defer_a_heavy_dependency():
    """There is no cycle left to break: an import of hyper's own inside a function is
    there only to keep a heavy package (`HEAVY`: DOLFINx, above all) off the paths that
    never need it, e.g. `hyper grow --ask signaling`, which runs the ODEs alone."""
    heavy = heavy_modules()
    found = [f"{path.relative_to(SRC.parent)}:{line}: {target}" for path in MODULES.values()
             for target, line, inner in imports(path) if inner and target not in heavy]
    assert found == [], "light hyper imports inside functions (import them at the top):\n" + "\n".join(found)


def test_the_heavy_closure_follows_module_level_imports():
    heavy = heavy_modules()
    assert heavy["hyper.fem.geometry"] in HEAVY and "hyper.runs.driver" in heavy
    assert "hyper.core.params" not in heavy and "hyper.model.protocols" not in heavy


def test_only_heavy_dependencies_are_imported_inside_functions():
    found = []
    for path in MODULES.values():
        tree = ast.parse(path.read_text())
        top = {id(n) for n in tree.body}
        guarded = {id(n) for node in tree.body if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                   for n in ast.walk(node)}
        for node in ast.walk(tree):
            if (isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in top | guarded
                    and not getattr(node, "level", 0)):
                names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                for name in names:
                    if name.split(".")[0] not in HEAVY and name.split(".")[0] != "hyper":
                        found.append(f"{path.relative_to(SRC.parent)}:{node.lineno}: {name}")
    assert found == [], "light imports inside functions (import them at the top):\n" + "\n".join(found)


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph`` with more than one member."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_check_finds_a_cycle():
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    graph = {name: {t for t, _, _ in imports(path) if t in MODULES and t != name} for name, path in MODULES.items()}
    assert strongly_connected(graph) == []


def test_the_layer_check_sees_an_upward_import():
    assert layer("hyper.fem.coupled") < layer("hyper.runs.driver") < layer("hyper.commands.grow") < layer("hyper.grow")
    assert layer("hyper.core.params") < layer("hyper.model.protocols")


def module_aliases(roots=(SRC, SRC.parents[1] / "tests")) -> dict[str, set[str]]:
    """The names each of hyper's modules is bound to where it is imported as a module."""
    out: dict[str, set[str]] = {}
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "hyper":
                    for alias in node.names:
                        if f"{node.module}.{alias.name}" in MODULES:
                            out.setdefault(f"{node.module}.{alias.name}", set()).add(alias.asname or alias.name)
                elif isinstance(node, ast.Import):
                    for alias in node.names:
                        if alias.name in MODULES and alias.asname:
                            out.setdefault(alias.name, set()).add(alias.asname)
    return out


def test_one_name_per_module():
    """A module reads the same wherever it is used (``geo`` for geometry, which the code's
    many ``geometry`` objects would shadow; ``X_job`` for a command beside its library)."""
    several = {module: sorted(names) for module, names in module_aliases().items() if len(names) > 1}
    assert several == {}
