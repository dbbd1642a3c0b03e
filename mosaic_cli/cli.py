"""The ``mosaic`` command line: thin wrappers that parse options and call the pipelines.

Every user mistake ends as one line on stderr and a non-zero exit (2 for bad input);
``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import sys

import typer

from mosaic_cli.errors import EXIT_FAILED, EXIT_INTERRUPTED, MosaicError

app = typer.Typer(
    name="mosaic",
    help="Stabilise aerial video and stitch it into panoramas with a learned sequential homography estimator.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

DEBUG = {"on": False}


@app.callback()
def _root(debug: bool = typer.Option(False, "--debug", help="Show full tracebacks on errors.")) -> None:
    DEBUG["on"] = debug


def _fail(message: str, code: int) -> None:
    sys.stderr.write(f"mosaic: error: {message}\n")
    sys.stderr.flush()
    raise SystemExit(code)


def _quiet_opencv() -> None:
    """OpenCV's warnings (a GeoTIFF's unknown tags, say) are not the user's business: errors only."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point."""
    if argv is None:
        argv = sys.argv[1:]
    DEBUG["on"] = "--debug" in argv
    if not DEBUG["on"]:
        _quiet_opencv()
    try:
        app(args=argv, standalone_mode=True)
    except MosaicError as exc:
        if DEBUG["on"]:
            raise
        _fail(str(exc), exc.exit_code)
    except KeyboardInterrupt:
        if DEBUG["on"]:
            raise
        _fail("interrupted", EXIT_INTERRUPTED)
    except SystemExit:
        raise
    except Exception as exc:  # a bug, not a user error: still one line unless --debug
        if DEBUG["on"]:
            raise
        _fail(f"{exc.__class__.__name__}: {exc} (run with --debug for the traceback)", EXIT_FAILED)


# Commands register themselves on ``app``; import them last.
from mosaic_cli.commands import bench, evaluate, simulate, stabilize, stitch, track, train  # noqa: E402,F401
