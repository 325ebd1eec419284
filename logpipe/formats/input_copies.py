"""Which of the inputs found are byte-identical copies of the inputs kept, for the ingest summary.

``logpipe.formats.inputs.fingerprint_inputs`` merges identical inputs into one ``SourceFile`` (with every copy's
memberships) and keeps no record of the copies; ``duplicate_inputs`` finds them again so a summary can say why
fewer inputs than files were ingested.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from logpipe.storage.io import sha256_file, sha256_tree
from logpipe.types import PENDING_SHA256, SourceFile


def duplicate_inputs(found: Sequence[tuple[Path, str]], sources: Sequence[SourceFile]) -> list[dict[str, str]]:
    """``{"path", "same_as"}`` (relative paths) for every input found that ``fingerprint_inputs`` merged into
    an identical one it kept, so a summary can say why fewer inputs than files were ingested.

    The merge keeps no record of the copies; a copy is matched to the kept input of its size, and hashed again
    only when several kept inputs have that size or when it is a folder (a bag).
    """
    kept = {s.relpath for s in sources}
    copies = [(path, rel) for path, rel in found if rel not in kept]
    if not copies:
        return []
    by_size: dict[int, list[SourceFile]] = {}
    for s in sources:
        if s.sha256 != PENDING_SHA256:  # a pending digest means no other input could equal it
            by_size.setdefault(s.size, []).append(s)
    out = []
    for path, rel in copies:
        if path.is_dir():  # a bag folder: matched by its digest, which every folder input has
            digest = sha256_tree(path)
            candidates = [s for s in sources if s.sha256 == digest]
        else:
            candidates = by_size.get(path.stat().st_size, [])
            if len(candidates) != 1:
                digest = sha256_file(path)
                candidates = [s for s in candidates if s.sha256 == digest]
        out.append({"path": rel, "same_as": candidates[0].relpath if candidates else "?"})
    return out
