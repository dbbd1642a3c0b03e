"""The ``mosaic`` command line: the typer app and the table of its commands (mosaic_cli/commands).

Every user mistake ends as one line on stderr and a non-zero exit (2 for bad input);
``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import atexit
import contextlib
import inspect
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

import typer

# Usage errors (unknown option, bad value, missing argument): typer's public base of its click
# exceptions since it carries its own copy of click; before that, click's own.
if hasattr(typer, "TyperException"):
    UsageProblem: type[Exception] = typer.TyperException
else:  # pragma: no cover - older typer, with click installed beside it
    from click.exceptions import ClickException as UsageProblem

from mosaic_cli.commands import bench, evaluate, simulate, stabilize, stitch, track, train
from mosaic_cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, MosaicError

app = typer.Typer(
    name="mosaic",
    help="Stabilise aerial video and stitch it into panoramas with a learned sequential homography estimator.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

DEBUG = {"on": False}


def package_version() -> str:
    """The installed package's version; a checkout run without installing falls back to
    pyproject.toml's, so that ``--version`` never fails."""
    from importlib import metadata

    try:
        return metadata.version("mosaic-cli")
    except metadata.PackageNotFoundError:
        import tomllib
        from pathlib import Path

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        try:
            return tomllib.loads(pyproject.read_text())["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def _print_version(wanted: bool) -> None:
    if wanted:
        print(f"mosaic {package_version()}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks on errors."),
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."),
) -> None:
    DEBUG["on"] = debug


def _fail(message: str, code: int) -> None:
    sys.stderr.write(f"mosaic: error: {message}\n")
    sys.stderr.flush()
    raise SystemExit(code)


def _quiet_opencv() -> None:
    """OpenCV's log (a GeoTIFF's unknown tags, libtiff's complaint about a damaged TIFF) is not the
    user's business: what fails reaches them as mosaic's own one line."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


# Signals end a run by unwinding it as Ctrl-C does, so that every temporary output is removed on
# the way out; which one arrived decides the message and the exit status (128 + signal).
SIGNAL_EXITS = {signal.SIGINT: ("interrupted", EXIT_INTERRUPTED), signal.SIGTERM: ("terminated", 128 + signal.SIGTERM)}
_received: list[int] = []


def _on_signal(signum, frame) -> None:
    _received.append(signum)
    raise KeyboardInterrupt


def _deliver_again_if_swallowed(unraisable) -> None:
    """Python swallows an exception raised where none can propagate (a fork hook while ffmpeg is
    started, a finaliser) and prints it: such an interrupt is sent again, to land in the run."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and _received:
        # From another thread, so that it arrives after this hook has returned, not inside it.
        threading.Timer(0.01, os.kill, (os.getpid(), _received[-1])).start()
        return
    sys.__unraisablehook__(unraisable)


@contextlib.contextmanager
def _stop_by_unwinding_on_signals() -> Iterator[None]:
    """Our handlers for the run, and the caller's back afterwards (main() also runs in-process)."""
    _received.clear()
    previous = {signum: signal.signal(signum, _on_signal) for signum in SIGNAL_EXITS}
    previous_hook, sys.unraisablehook = sys.unraisablehook, _deliver_again_if_swallowed
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        sys.unraisablehook = previous_hook


def _fail_stopped() -> None:
    """The one line for a run stopped by a signal (Ctrl-C when typer swallowed which one)."""
    _fail(*SIGNAL_EXITS[_received[0] if _received else signal.SIGINT])


def _usage_message(exc: Exception) -> str:
    """Click's usage errors as one line that says where the help is."""
    ctx = getattr(exc, "ctx", None)
    where = f" (see {ctx.command_path} --help)" if ctx is not None else ""
    message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
    return f"{message}{where}"


def entry() -> None:
    """The console script (and ``python -m mosaic_cli``): :func:`main`, then a quick exit.

    Everything is written and closed when :func:`main` returns; tearing down an interpreter
    that has loaded torch takes another 0.4 s (CHANGELOG.md, speed, 2026-11-27), a third of a short
    command's start-up.  So the exit handlers run, the streams are flushed and any worker
    thread still running is waited for, then the process ends without the teardown."""
    if sys.getprofile() is not None or sys.gettrace() is not None:
        main()  # a profiler or a coverage tool writes its data at the teardown: keep it
        return
    try:
        main()
        code: int | str | None = 0
    except SystemExit as exc:
        code = exc.code
    if isinstance(code, str):  # SystemExit("message"): Python prints it and exits 1
        print(code, file=sys.stderr)
        code = 1
    try:
        _wait_for_threads()
    except KeyboardInterrupt:  # a second Ctrl-C while a writer finishes: the one line, not a traceback
        sys.stderr.write("mosaic: error: interrupted\n")
        code = EXIT_INTERRUPTED
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: nothing left to say
            stream.flush()
    os._exit(code or 0)


def _wait_for_threads() -> None:
    """Wait for the threads still running, as the interpreter does at its exit: idle thread-pool
    workers (a library's, or an estimator's that nobody closed) are told to end first, since
    they wait for work that will never come; then every other thread that is not a daemon."""
    from concurrent.futures import thread as pool_threads

    wake_idle_workers = getattr(pool_threads, "_python_exit", None)  # CPython's own exit hook for them
    if wake_idle_workers is not None:
        wake_idle_workers()
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()


def main(argv: list[str] | None = None) -> None:
    """The command line: ``argv`` (the process's arguments when None); ends in SystemExit."""
    if argv is None:
        argv = sys.argv[1:]
    if not [a for a in argv if a != "--debug"]:
        argv = [*argv, "--help"]
    DEBUG["on"] = "--debug" in argv
    if DEBUG["on"]:  # accepted anywhere on the line, not only before the command
        argv = ["--debug", *(a for a in argv if a != "--debug")]
    else:
        _quiet_opencv()
    with _stop_by_unwinding_on_signals():
        _run(argv)


def _run(argv: list[str]) -> None:
    try:
        code = app(args=argv, prog_name="mosaic", standalone_mode=False)
    except UsageProblem as exc:  # a usage error: unknown option, bad value, missing argument
        _fail(_usage_message(exc), EXIT_BAD_INPUT)
    except MosaicError as exc:
        if DEBUG["on"]:
            raise
        _fail(str(exc), exc.exit_code)
    except (KeyboardInterrupt, typer.Abort):
        if DEBUG["on"]:
            raise
        _fail_stopped()
    except SystemExit:
        raise
    except Exception as exc:
        if DEBUG["on"]:
            raise
        if _received:  # a signal that cut an import or a library call short, whatever it raised
            _fail_stopped()
        if isinstance(exc, OSError) and exc.strerror:  # the machine's, not a bug: disk full, I/O error
            _fail(f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror, EXIT_FAILED)
        _fail(f"{exc.__class__.__name__}: {exc} (run with --debug for the traceback)", EXIT_FAILED)
    if _received or code == EXIT_INTERRUPTED:  # typer turns a KeyboardInterrupt into status 130 on its own
        _fail_stopped()
    raise SystemExit(code or 0)


def _flags_take_no_value_in_help() -> None:
    """typer's rich help gives every flag (``-q``, ``--help``, ``--no-drift-control``) a
    ``<bool>`` type column, which reads as ``-q true``; a flag takes no value: show none."""
    from typer.core import TyperOption

    shown = getattr(TyperOption, "display_type_rich", None)
    if shown is None or getattr(shown, "mosaic_flags", False):  # a typer without that column: nothing to mend
        return

    def display_type_rich(self, ctx):
        return None if getattr(self, "is_flag", False) else shown(self, ctx)

    display_type_rich.mosaic_flags = True
    TyperOption.display_type_rich = display_type_rich


_flags_take_no_value_in_help()

# The commands, in the order ``mosaic --help`` lists them: plain functions whose parameters
# declare their flags; each is registered here and imports nothing of this module.
COMMANDS = {
    "bench": bench.bench,
    "eval": evaluate.evaluate,
    "simulate": simulate.simulate,
    "stabilize": stabilize.stabilize,
    "stitch": stitch.stitch,
    "track": track.track,
    "train": train.train,
}


def _help_of(command: Callable[..., Any]) -> str:
    """A command's docstring as its ``--help`` shows it: each paragraph one flowing line, which
    rich wraps to the terminal (the docstring's own line ends, kept, broke lines mid-sentence),
    and brackets escaped (rich read ``pairwise[t]`` as markup and dropped the ``[t]``)."""
    from rich.markup import escape

    paragraphs = inspect.cleandoc(command.__doc__ or "").split("\n\n")
    return "\n\n".join(escape(" ".join(paragraph.split())) for paragraph in paragraphs)


for _name, _command in COMMANDS.items():
    app.command(_name, help=_help_of(_command))(_command)
