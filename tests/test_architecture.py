"""The layer rules of ``docs/architecture.md``, checked on the real imports (parsed, not executed).

Core (``logpipe/``) never imports ``model/`` and imports ``stages/`` only inside ``logpipe/api.py``'s functions;
stages never import each other; ``model/`` imports core only; the core packages import only their own layer or a
lower one (``LAYERS``); every module outside tests stays near 500 lines, stage modules near 300, and function bodies
near 80. Inside ``model/`` (``MODEL_LAYERS``): at most 8 modules at the top, a package per predictor family that imports
``training``, ``checkpoint`` and ``kinematic`` but never another family, and no import circle among its modules.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 520  # docs/architecture.md: "no module outside tests exceeds ~500 lines"
MAX_STAGE_LINES = 300
MAX_BODY_LINES = 80  # statements of a function, its signature and docstring not counted

LAYERS = {  # docs/architecture.md §1: a module may import its own layer or a lower one, never a higher one
    "vocabulary": 0,  # logpipe/*.py: types, errors, contracts, geometry, executor, progress, summaries
    "storage": 1, "dataset": 2, "formats": 3, "maps": 3, "raster": 4, "mcap": 4, "synthetic": 4,
    "prediction": 5, "scoring": 6, "model": 6, "stages": 7, "entry": 8, "cli": 9,
}
MODEL_LAYERS = {  # docs/architecture.md §1, model/__init__.py: a package imports its own layer or a lower one
    "training": 0, "checkpoint": 1, "kinematic": 1, "zhu2020": 2, "residual": 2, "social_lstm": 2, "social_gan": 2,
    "top": 3,
}
# predictor families: a family never imports another one
MODEL_FAMILIES = {"zhu2020", "residual", "social_lstm", "social_gan"}
MAX_TOP_MODEL_MODULES = 8
ENTRY_POINTS = {"api", "options", "inspect", "verify"}  # logpipe/<name>.py: the commands' Python side


def _layer(module: str) -> str | None:
    """The layer of a ``logpipe`` module name (``stages``/``model`` under their installed names); None outside."""
    parts = module.split(".")
    if parts[0] != "logpipe":
        return None
    if len(parts) == 1:
        return "vocabulary"
    if parts[1] in LAYERS:
        return parts[1]
    return "entry" if parts[1] in ENTRY_POINTS else "vocabulary"


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(imported module, at module level?) for every import of ``path``, relative ones resolved to absolute names."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, id(node) in top) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = _absolute(path, node)
            if module is not None:
                found.append((module, id(node) in top))
    return found


def _absolute(path: Path, node: ast.ImportFrom) -> str | None:
    """The absolute module name of ``from X import ...`` in ``path`` (``from . import y`` gives the package)."""
    if node.level == 0:
        return node.module
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _modules(folder: str) -> list[Path]:
    return sorted((REPO / folder).rglob("*.py"))


def test_core_never_imports_model_and_stages_only_lazily_from_the_api() -> None:
    for path in _modules("logpipe"):
        for name, top_level in _imports(path):
            assert not name.startswith("logpipe.model"), f"{path}: imports {name}"
            if name.startswith("logpipe.stages"):
                assert path.name == "api.py" and not top_level, f"{path}: imports {name}"


def test_stages_never_import_each_other_and_model_imports_only_core() -> None:
    for path in _modules("stages"):
        own = f"logpipe.stages.{path.stem}"
        for name, _ in _imports(path):
            assert not name.startswith("logpipe.stages") or name == own, f"{path}: imports {name}"
    for path in _modules("model"):
        for name, _ in _imports(path):
            assert not name.startswith("logpipe.stages"), f"{path}: imports {name}"


def test_no_module_outside_tests_is_much_over_500_lines() -> None:
    sizes = {p: len(p.read_text().splitlines()) for folder in ("logpipe", "stages", "model", "scripts", "benchmarks")
             for p in _modules(folder)}
    assert len(sizes) > 100
    assert {str(p.relative_to(REPO)): n for p, n in sizes.items() if n > MAX_LINES} == {}


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
    return ".".join(parts if parts[0] == "logpipe" else ["logpipe", *parts])


def test_core_packages_import_only_their_layer_or_lower() -> None:
    checked = 0
    for folder in ("logpipe", "stages", "model"):
        for path in _modules(folder):
            source = _layer(_module_name(path))
            assert source is not None
            for name, top_level in _imports(path):
                target = _layer(name)
                if target is None or (path.name == "__init__.py" and path.parent.name == "logpipe" and not top_level):
                    continue  # third-party, or the package's lazy ``logpipe.ingest`` → ``logpipe.api``
                checked += 1
                assert LAYERS[target] <= LAYERS[source], f"{path}: {source} imports {name} ({target})"
    assert checked > 300


def test_stage_modules_only_orchestrate_and_functions_stay_short() -> None:
    stage_sizes = {p.name: len(p.read_text().splitlines()) for p in _modules("stages")}
    assert {n: s for n, s in stage_sizes.items() if s > MAX_STAGE_LINES} == {}
    long_bodies = {}
    for folder in ("logpipe", "stages", "model", "scripts", "benchmarks"):
        for path in _modules(folder):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    body = node.body[1:] if ast.get_docstring(node) is not None else node.body
                    lines = body[-1].end_lineno - body[0].lineno + 1 if body else 0  # type: ignore[operator]
                    if lines > MAX_BODY_LINES:
                        long_bodies[f"{path.relative_to(REPO)}:{node.name}"] = lines
    assert long_bodies == {}


def _model_package(module: str) -> str | None:
    """The ``model/`` package of a ``logpipe.model`` module name (``top`` for the modules at its top); None outside."""
    parts = module.split(".")
    if parts[:2] != ["logpipe", "model"]:
        return None
    if len(parts) == 2:
        return "top"
    return parts[2] if (REPO / "model" / parts[2]).is_dir() else "top"


def test_model_is_a_few_top_modules_and_a_package_per_family() -> None:
    top = sorted(p.name for p in (REPO / "model").glob("*.py") if p.name != "__init__.py")
    packages = sorted(p.name for p in (REPO / "model").iterdir() if (p / "__init__.py").is_file())
    assert len(top) <= MAX_TOP_MODEL_MODULES, top
    assert len(packages) >= 4 and set(packages) == set(MODEL_LAYERS) - {"top"}, packages
    for package in packages:  # each says what it holds and what it may import
        doc = ast.get_docstring(ast.parse((REPO / "model" / package / "__init__.py").read_text()))
        assert doc is not None and "Imports:" in doc, package


def test_model_packages_import_only_their_layer_or_lower_and_no_other_family() -> None:
    checked = 0
    for path in _modules("model"):
        source = _model_package(_module_name(path))
        assert source is not None
        for name, _ in _imports(path):  # lazy imports inside functions count too
            target = _model_package(name)
            if target is None or target == source:
                continue
            checked += 1
            assert MODEL_LAYERS[target] <= MODEL_LAYERS[source], f"{path}: {source} imports {name} ({target})"
            assert not (source in MODEL_FAMILIES and target in MODEL_FAMILIES), f"{path}: family imports {name}"
            if MODEL_LAYERS[target] == MODEL_LAYERS[source]:  # checkpoint and kinematic: neither imports the other
                raise AssertionError(f"{path}: {source} imports {name} of its own layer ({target})")
    assert checked > 25


def _all_imports(path: Path) -> set[str]:
    """Every ``logpipe.model`` module ``path`` imports, at any level (``from pkg import module`` included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (module := _absolute(path, node)) is not None:
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names}
    return {n for n in found if n.startswith("logpipe.model")}


def test_no_import_circle_among_model_modules() -> None:
    modules = {_module_name(p): p for p in _modules("model")}
    graph = {name: {m for m in _all_imports(path) if m in modules and m != name and not name.startswith(m + ".")}
             for name, path in modules.items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                raise AssertionError("import circle: " + " -> ".join([*stack[stack.index(nxt):], nxt]))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name)
    assert len(graph) > 40
