"""The layer rules of ``docs/architecture.md``, checked on the real imports (parsed, not executed).

Core (``logpipe/``) never imports ``model/`` and imports ``stages/`` only inside ``logpipe/api.py``'s functions;
stages never import each other; ``model/`` imports core only; every module outside tests stays near 500 lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 520  # docs/architecture.md: "no module outside tests exceeds ~500 lines"


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
