"""``record_written_files`` proves what ``record_written`` proves, file by file, in one append per artifact root."""

from __future__ import annotations

from pathlib import Path

from logpipe.storage.folder_lock import LOCK_FILE
from logpipe.storage.write_journal import JOURNAL, read_journal, record_written, record_written_files, start_journal


def test_batch_record_proves_each_file_like_one_by_one(tmp_path: Path) -> None:
    roots = [tmp_path / "a", tmp_path / "b"]
    for root in roots:
        (root / "mcap" / "part-00000").mkdir(parents=True)
        (root / LOCK_FILE).write_text("")
        start_journal(root)
    files = [root / "mcap" / "part-00000" / f"{i}.mcap" for root in roots for i in range(3)]
    for i, path in enumerate(files):
        path.write_bytes(bytes(i + 1))
    outside = tmp_path / "free.mcap"  # no locked folder above it: recorded nowhere
    outside.write_bytes(b"x")
    record_written_files([*files[:3], outside, roots[0] / "manifest.json", *files[3:]])
    for root in roots:
        journal = read_journal(root)
        mine = [p for p in files if root in p.parents]
        assert all(journal.proves(root, p) for p in mine)
        # One append per root, the same entries record_written writes one by one.
        batch = (root / JOURNAL).read_text()
        (root / JOURNAL).write_text("")
        for p in mine:
            record_written(p)
        assert (root / JOURNAL).read_text() == batch
        assert batch.count("\n") == 3
    edited = files[0]
    edited.write_bytes(b"changed, so no longer the file recorded")
    assert not read_journal(roots[0]).proves(roots[0], edited)
