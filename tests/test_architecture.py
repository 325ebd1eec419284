"""The layer rules of ``docs/architecture.md``, checked on the real imports (parsed, not executed).

Core (``logpipe/``) never imports ``model/`` and imports ``stages/`` only inside ``logpipe/api.py``'s functions;
stages never import each other; ``model/`` imports core only; the core packages import only their own layer or a
lower one (``LAYERS``); every module outside tests stays near 500 lines, stage modules near 300, and function bodies
near 80.
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
    """(imported module, at module level?) for every import of ``path``, relative ones resolved in ``logpipe``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, id(node) in top) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module is not None and node.level == 0:
            found.append((node.module, id(node) in top))
    return found


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
