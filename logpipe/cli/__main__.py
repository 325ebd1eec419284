"""``python -m logpipe.cli``: the ``logpipe`` command."""

from logpipe.cli import app

if __name__ == "__main__":  # pragma: no cover
    app()
