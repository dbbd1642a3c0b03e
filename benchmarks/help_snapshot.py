"""The ``--help`` of mosaic and of every command, as plain text, to diff a refactor against.

    python -m benchmarks help-snapshot > /tmp/help_before.txt      # before the change
    python -m benchmarks help-snapshot > /tmp/help_after.txt       # after it
    diff /tmp/help_before.txt /tmp/help_after.txt               # nothing, if the CLI is unchanged

Each help is rendered in-process at a fixed width, without colour, so that two runs on different
terminals give the same text and only a change to the command line shows in the diff.
"""

from __future__ import annotations

import os
import sys

# rich reads the width and colour when it renders, from the environment: fixed before typer
# renders anything, so that the terminal this runs in does not change the text.
os.environ["COLUMNS"] = "120"
os.environ["NO_COLOR"] = "1"
os.environ["TERM"] = "dumb"

from typer.testing import CliRunner  # noqa: E402

from benchmarks.common import make_parser  # noqa: E402
from mosaic_cli.cli import COMMANDS, app  # noqa: E402

SUITE = "help-snapshot"


def help_text(args: list[str]) -> str:
    """What ``mosaic ARGS --help`` prints."""
    result = CliRunner().invoke(app, [*args, "--help"], prog_name="mosaic", terminal_width=120, color=False)
    if result.exit_code != 0:
        raise SystemExit(f"mosaic {' '.join(args)} --help exited {result.exit_code}: {result.output}")
    return result.output


def main(argv: list[str] | None = None) -> int | None:
    make_parser(SUITE, None, __doc__).parse_args(argv)
    for args in [[], *([name] for name in COMMANDS)]:
        sys.stdout.write(f"===== mosaic {' '.join([*args, '--help'])}\n")
        sys.stdout.write(help_text(args))
