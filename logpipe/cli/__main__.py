"""``python -m logpipe.cli``: the ``logpipe`` command."""

from logpipe.cli import main

if __name__ == "__main__":  # pragma: no cover
    main()
