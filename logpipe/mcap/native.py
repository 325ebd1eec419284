"""MCAP files through the Rust MCAP writer inside ``foxglove-sdk``: what predict copies an original MCAP with when
it cannot copy it by chunk but this writer keeps every field (``logpipe.mcap.merge``). Ingest's MCAPs and predict's
others are laid out by ``logpipe.mcap.bulk`` since issue 66 (``docs/bench.md``: fed the same batch-built messages,
this writer measured the same end to end, and it cannot copy chunks).

Why this writer: on our own records (``make bench``'s ``mcap_writers``) it writes ~5-8x as many records per CPU
second as the pure-Python ``mcap`` writer, whose per-record Python work was most of ingest's MCAP cost; the files
carry the same summary, chunk indexes, message indexes and CRCs (chunks zstd-compressed).

What it decides itself (and the ``mcap`` writer leaves to the caller), so what a file written here always has:

* sequence numbers 1, 2, ... per channel in the order messages are logged, and publish time = log time;
* channel ids 1, 2, ... and schema ids 1, 2, ... in the order of each channel's first message (a channel that
  never gets a message is not written at all), identical schemas written once;
* the header's ``library`` names the SDK (``foxglove-sdk-python/<v> mcap-rust/<v>``); its ``profile`` is ours.

Each file gets its own ``foxglove.Context``, so channels of different files (or threads) never mix. Channels are
made with ``Context._create_channel`` (what ``foxglove.Channel`` calls): ``foxglove.Channel`` also keeps every
channel in a module-level dict for ever, which at one MCAP per log would grow with every log ingested.
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path
from types import TracebackType
from typing import Any

import foxglove
from foxglove.mcap import MCAPWriteOptions

from logpipe.storage.write_journal import record_written

# The SDK logs one line per message it could not write (a full disk: thousands) and then fails the file's
# ``close`` with one error, which ``_as_os_error`` turns into the same one line as any full disk.
logging.getLogger("foxglove").setLevel(logging.CRITICAL)

_FREE_BYTES_FULL = 1 << 20
"""Free space under which an SDK "I/O error" on writing is taken for a full disk (the SDK does not say which)."""


def _as_os_error(err: RuntimeError, target: Path) -> OSError | RuntimeError:
    """The SDK's ``RuntimeError('FoxgloveError: MCAP error: I/O error ...')`` as the ``OSError`` it stands for:
    ENOSPC when the target's file system is (nearly) full, else EIO; any other error as it is."""
    if "I/O error" not in str(err):
        return err
    try:
        stats = os.statvfs(target.parent)
        full = stats.f_bavail * stats.f_frsize < _FREE_BYTES_FULL
    except OSError:
        full = False
    code = errno.ENOSPC if full else errno.EIO
    return OSError(code, os.strerror(code), str(target))


class NativeMcap:
    """One MCAP file being written (use as a context manager; the file is finished on exit)."""

    def __init__(self, target: Path, profile: str = "", compression_threads: int = 0) -> None:
        """``compression_threads``: 0 compresses each chunk in the logging call, n > 0 on n threads of the SDK
        while the caller goes on (the same CPU, less waiting where a file has many chunks)."""
        self._target = target
        self._context = foxglove.Context()
        options = MCAPWriteOptions(profile=profile, compression_threads=compression_threads)
        self._writer = foxglove.open_mcap(target, allow_overwrite=True, context=self._context,
                                          writer_options=options)

    def channel(self, topic: str, message_encoding: str, schema: tuple[str, str, bytes] | None,
                metadata: dict[str, str] | None = None) -> Any:
        """A channel of this file; ``schema`` is (name, encoding, data). Log with ``.log(data, log_time, None)``."""
        fx_schema = None if schema is None else foxglove.Schema(name=schema[0], encoding=schema[1], data=schema[2])
        return self._context._create_channel(topic, message_encoding=message_encoding, schema=fx_schema,
                                             metadata=metadata or None)

    def metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record (the SDK writes none for an empty dict)."""
        self._writer.write_metadata(name, values)

    def attach(self, *, log_time: int, create_time: int, name: str, media_type: str, data: bytes) -> None:
        """An attachment record."""
        self._writer.attach(log_time=log_time, create_time=create_time, name=name, media_type=media_type, data=data)

    def close(self) -> None:
        """Write the summary and footer and close the file (a write the SDK failed is an ``OSError`` here)."""
        try:
            self._writer.close()
        except RuntimeError as err:
            raise _as_os_error(err, self._target) from None
        record_written(self._target)  # written in place (in staging): the proof a later cleanup needs

    def __enter__(self) -> NativeMcap:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
