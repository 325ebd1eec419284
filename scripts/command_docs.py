"""``docs/commands/<command>.md``: one page per ``logpipe`` command, its ``--help`` as the command prints it piped
(plain text, 100 columns). ``python -m scripts.command_docs`` rewrites them; ``--check`` exits 1 naming the pages
that differ from what the commands print now (``tests/scripts/test_command_docs.py`` runs it)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs" / "commands"
WIDTH = 100


def pages() -> dict[str, str]:
    """Page text by command, in ``logpipe --help``'s order."""
    import typer
    from typer.testing import CliRunner

    from logpipe.cli import app

    app.rich_markup_mode = None  # the plain help a pipe gets, whatever this process's stdout is
    commands = list(typer.main.get_command(app).commands)  # type: ignore[attr-defined]
    out = {}
    for name in commands:
        result = CliRunner().invoke(app, [name, "--help"], prog_name="logpipe", terminal_width=WIDTH,
                                    env={"COLUMNS": str(WIDTH)})
        if result.exit_code != 0:
            raise SystemExit(f"logpipe {name} --help failed: {result.output}")
        body = "\n".join(line.rstrip() for line in result.stdout.strip().splitlines())
        note = (f"<!-- generated from `logpipe {name} --help` by `python -m scripts.command_docs`; edit the "
                "command's help, not this page -->")
        out[name] = (f"# logpipe {name}\n\n{note}\n\n```text\n{body}\n```\n\n"
                     "More: [the guide](../guide.md), [the README](../../README.md).\n")
    return out


def main(argv: list[str] | None = None) -> int:
    """Write the pages (or with ``--check`` compare them); returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    parser.add_argument("--out", type=Path, default=DOCS)
    args = parser.parse_args(argv)
    stale = []
    for name, text in pages().items():
        path = args.out / f"{name}.md"
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(str(path))
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    if stale:
        print("stale command pages (run python -m scripts.command_docs): " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
