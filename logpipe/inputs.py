"""Finding and fingerprinting inputs: paths → ``SourceFile`` records with sha256 and folder-layout labels."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from logpipe.errors import LogpipeError
from logpipe.formats.base import FormatAdapter
from logpipe.io import sha256_tree
from logpipe.types import SourceFile

SPLITS = ("train", "val", "test")


def memberships_from_layout(relpath: str) -> tuple[str, ...]:
    """``("<scene>/<split>",)`` when a path ends in ``<scene>/<train|val|test>/<file>``, else ()."""
    parts = Path(relpath).parts
    if len(parts) >= 3 and parts[-2] in SPLITS:
        return (f"{parts[-3]}/{parts[-2]}",)
    return ()


def collect_sources(roots: Sequence[Path], adapter: FormatAdapter, threads: int = 4) -> list[SourceFile]:
    """Every input the adapter finds under ``roots``, hashed, with identical contents merged into one.

    Merging identical files is what lets ETH/UCY's repeated ``*_train.txt`` copies become one log whose
    ``memberships`` list every scene folder it appears in. Sorted by relative path (deterministic shards).

    Raises:
        LogpipeError: a root does not exist or holds nothing this format reads.
    """
    found: list[tuple[Path, str]] = []
    for root in roots:
        if not root.exists():
            raise LogpipeError(f"{root}: no such file or folder")
        paths = adapter.discover(root)
        if not paths:
            raise LogpipeError(f"{root}: no {adapter.name} inputs found")
        # A root that is itself one input (a file, or a bag folder) is named by its own name, not ".".
        base = root.parent if root.is_file() or paths == [root] else root
        found.extend((p, p.relative_to(base).as_posix()) for p in paths)
    found.sort(key=lambda item: item[1])
    # hashlib releases the GIL: a few threads, each over a contiguous slice (one task per file costs more
    # in executor overhead than hashing a 90 kB CSV).
    slices = [found[i::threads] for i in range(threads)]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        parts = list(pool.map(lambda part: [sha256_tree(p) for p, _ in part], slices))
    digests = [""] * len(found)
    for i, part in enumerate(parts):
        digests[i::threads] = part
    by_digest: dict[str, SourceFile] = {}
    for (path, relpath), digest in zip(found, digests, strict=True):
        labels = memberships_from_layout(relpath)
        if digest in by_digest:
            first = by_digest[digest]
            merged = tuple(sorted(set(first.memberships) | set(labels)))
            by_digest[digest] = SourceFile(first.path, first.relpath, digest, first.size, merged)
        else:
            size = path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*"))
            by_digest[digest] = SourceFile(str(path), relpath, digest, size, labels)
    return sorted(by_digest.values(), key=lambda s: s.relpath)
