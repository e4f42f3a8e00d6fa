"""The package layering of CONTRIBUTING.md, checked by reading every import (issue #20).

Every ``import`` / ``from ... import`` statement is read with :mod:`ast`, including imports inside functions and
``TYPE_CHECKING`` blocks (an import hidden in a function is still a dependency). Checked:

- no import cycles between modules (strongly connected components of the module graph);
- every import points to the same layer or a lower one, in the flow's order (``LAYERS``; inside the optimiser the
  core, the baselines, the method registry, the run spec and the run driver are layers of their own, so the
  baselines and the optimiser never import each other in a circle);
- ``evaluation.metrics`` imports only itself and ``camo_base`` (metrics work on any images, without Mitsuba);
- ``camo_base`` imports no heavy library at module level (every package may import it cheaply).

The checker itself is tested on a small synthetic tree, so a broken reader cannot pass silently.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("camo_base", "optimizer", "evaluation", "study_site", "camo")
#: Lowest first; a module may import its own layer and any layer before it. The longest matching prefix wins.
LAYERS = (
    "camo_base",
    "optimizer",  # the package root and optimizer.backend (the Mitsuba / Dr.Jit runtime)
    "optimizer.scenes",
    "optimizer.rendering",
    "optimizer.assets",
    "optimizer.optimise",  # the core: losses, Adam, stages, searches, warm start, inpainting, presets, options
    "optimizer.optimise.baselines",  # the baselines use the core, never the method registry or the run driver
    "optimizer.optimise.methods",  # the method registry: ours and every baseline module's METHODS
    "optimizer.optimise.spec",  # the run spec (names methods)
    "optimizer.optimise.run",  # the run driver
    "evaluation",
    "study_site",
    "camo",
)
HEAVY = ("mitsuba", "drjit", "torch", "kornia", "pandas", "matplotlib", "flask", "sqlalchemy", "scipy", "skimage")


def module_names(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """``{dotted module name: file}`` for every ``.py`` file of ``packages`` under ``root``."""
    out = {}
    for pkg in packages:
        for p in sorted((root / pkg).rglob("*.py")):
            name = ".".join(p.relative_to(root).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = p
    return out


#: ``"package.module:callable"`` or ``"package.module"``: a string that names one of our modules is a hidden import.
_MODULE_STRING = re.compile(r"^\w+(?:\.\w+)+(?::[\w.]+)?$|^\w+:[\w.]+$")
#: Calls that import by name: ``importlib.import_module("x.y")``, ``__import__("x.y")``, and
#: ``camo_base.plugins.submodules("pkg")`` (every module of ``pkg``: a registry's discovery).
_IMPORT_CALLS = ("import_module", "__import__")
_DISCOVERY_CALLS = ("submodules",)


def _call_name(node: ast.Call) -> str:
    f = node.func
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def dynamic_imports(tree: ast.AST) -> list[tuple[str, int, str]]:
    """``(target, line, how)`` of the imports a module makes by name: literal arguments of import calls,
    discovery calls (target ``pkg.*``) and strings naming one of our modules (``"module:callable"``); ``how`` is
    ``"dynamic"`` for an import call whose argument is not a literal (its target is unknown)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and _call_name(node) in _IMPORT_CALLS + _DISCOVERY_CALLS and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                star = ".*" if _call_name(node) in _DISCOVERY_CALLS else ""
                out.append((arg.value + star, node.lineno, "call"))
            else:
                out.append(("?", node.lineno, "dynamic"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and _MODULE_STRING.match(node.value):
            out.append((node.value.partition(":")[0], node.lineno, "string"))
    return out


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """``(imported module, line, at module level)`` for each import of one of ``modules`` in ``path``; an
    imported name that is not a module counts as its module. Imports by name count too (:func:`dynamic_imports`:
    a literal ``importlib.import_module`` target, every module of a package a registry discovers, a
    ``"module:callable"`` string); they are never "at module level"."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top = {id(n) for n in tree.body}
    out = []
    docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
                  and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and id(node) in docstrings:
            continue
        if isinstance(node, (ast.Call, ast.Constant)):
            for target, line, how in dynamic_imports(node) if isinstance(node, ast.Call) else \
                    dynamic_imports(ast.Expression(node)):
                if how == "dynamic":
                    continue
                if target.endswith(".*"):
                    pkg = target[:-2]
                    hits = [m for m in modules if m.startswith(pkg + ".") and "." not in m[len(pkg) + 1:]]
                else:
                    hits = [target]
                for t in hits:
                    while t and t not in modules:
                        t = t.rpartition(".")[0]
                    # (a module's own packages are imported before it: naming one adds no dependency)
                    if t and t != name and not name.startswith(t + "."):
                        out.append((t, line, False))
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join(parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            targets = [f"{base}.{a.name}" for a in node.names] or [base]
        else:
            continue
        for t in targets:
            while t and t not in modules:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.append((t, node.lineno, id(node) in top))
    return out


def graph(root: Path, packages=PACKAGES) -> tuple[dict[str, set[str]], dict[tuple[str, str], int]]:
    mods = module_names(root, packages)
    edges: dict[str, set[str]] = {m: set() for m in mods}
    lines: dict[tuple[str, str], int] = {}
    for m, p in mods.items():
        for t, line, _ in imports_of(m, p, mods):
            edges[m].add(t)
            lines.setdefault((m, t), line)
    return edges, lines


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def layer_of(module: str, layers=LAYERS) -> int:
    best = -1
    for i, prefix in enumerate(layers):
        if module == prefix or module.startswith(prefix + "."):
            if best < 0 or len(prefix) > len(layers[best]):
                best = i
    if best < 0:
        raise AssertionError(f"{module} is in no layer")
    return best


def upward(edges, lines, layers=LAYERS) -> list[str]:
    return [f"{m}:{lines[(m, t)]} imports {t} (layer {layers[layer_of(t, layers)]} is above {layers[layer_of(m, layers)]})"
            for m in sorted(edges) for t in sorted(edges[m]) if layer_of(t, layers) > layer_of(m, layers)]


# --- the checker on a synthetic tree ------------------------------------------------------------------------


def test_the_checker_finds_cycles_and_upward_imports_on_a_known_tree(tmp_path):
    files = {
        "low/__init__.py": "",
        "low/a.py": "from low import b\n",
        "low/b.py": "def f():\n    from . import a\n",  # cycle hidden in a function
        "high/__init__.py": "",
        "high/c.py": "import low.a\nfrom low.b import f\n",
        "low/d.py": "from high.c import x\n",  # upward
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    edges, lines = graph(tmp_path, ("low", "high"))
    assert edges["high.c"] == {"low.a", "low.b"}
    assert cycles(edges) == [["low.a", "low.b"]]
    assert upward(edges, lines, ("low", "high")) == ["low.d:1 imports high.c (layer high is above low)"]


def test_the_checker_reads_imports_by_name(tmp_path):
    """``importlib.import_module("x")``, ``"module:callable"`` strings and a registry's discovery call are imports
    too; a docstring naming a module is not."""
    files = {
        "low/__init__.py": "",
        "low/a.py": '"""See low.b for more."""\nimport importlib\ndef f():\n    return importlib.import_module("low.b")\n',
        "low/b.py": 'REF = "low.c:make"\n',
        "low/c.py": "from camo_base.plugins import submodules\nPLUGINS = submodules(\"low.plug\")\n",
        "low/plug/__init__.py": "",
        "low/plug/one.py": "import low.a\n",
        "low/plug/two.py": "",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    edges, _ = graph(tmp_path, ("low",))
    assert edges["low.a"] == {"low.b"}
    assert edges["low.b"] == {"low.c"}
    assert edges["low.c"] == {"low.plug", "low.plug.one", "low.plug.two"}
    assert cycles(edges) == [["low.a", "low.b", "low.c", "low.plug.one"]]


# --- the real tree ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real():
    return graph(ROOT)


def test_every_module_is_in_a_layer(real):
    edges, _ = real
    assert len(edges) > 90  # 100 modules on 2026-11-23: the reader found the tree
    for m in edges:
        layer_of(m)


def test_no_import_cycles(real):
    edges, _ = real
    assert cycles(edges) == []


def test_imports_point_down_the_flow(real):
    edges, lines = real
    assert upward(edges, lines) == []


def test_metrics_depend_on_nothing_but_camo_base(real):
    edges, lines = real
    bad = [f"{m}:{lines[(m, t)]} imports {t}" for m in edges if m.startswith("evaluation.metrics")
           for t in edges[m] if not (t.startswith("evaluation.metrics") or t.startswith("camo_base"))]
    assert bad == []


def test_camo_base_imports_no_heavy_library_at_module_level():
    bad = []
    for name, path in module_names(ROOT, ("camo_base",)).items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                bad += [f"{name}:{node.lineno} {n}" for n in names if n.split(".")[0] in HEAVY]
    assert bad == []


def test_evaluation_and_the_study_never_need_the_optimiser(real):
    """Evaluating anyone's result reads it through optimizer.assets and renders it with optimizer.rendering; nothing
    in evaluation or study_site imports optimizer.optimise (Stage 1/2, baselines, the run driver)."""
    edges, lines = real
    bad = [f"{m}:{lines[(m, t)]} imports {t}" for m in edges if m.split(".")[0] in ("evaluation", "study_site")
           for t in edges[m] if t.startswith("optimizer.optimise")]
    assert bad == []


#: Modules allowed to import by a computed name, and why (every other import names its module literally).
DYNAMIC_IMPORTS_ALLOWED = {
    "camo_base.plugins": "the registries' discovery (its callers name their package literally; read above)",
    "optimizer.optimise.inpainting.diffusers_backend": "third-party diffusers / transformers modules only",
}


def test_no_import_by_a_computed_name():
    bad = []
    for name, path in module_names(ROOT).items():
        if name in DYNAMIC_IMPORTS_ALLOWED:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        bad += [f"{name}:{line}" for _, line, how in dynamic_imports(tree) if how == "dynamic"]
    assert bad == []
