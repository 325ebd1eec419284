"""``make bench``'s modules. ``logpipe`` is imported first so that its OpenMP setting (``logpipe/__init__.py``)
is in place before any benchmark loads torch, as in every ``logpipe`` command."""

import logpipe  # noqa: F401
