"""Entry point of the ``lungdeform`` command.

Each command lives in its own module under ``lungdeform.cli`` and exposes ``register(apps)``, where
``apps`` is :class:`Apps` (the root app and the ``validate`` and ``bench`` groups). Add a module's
name to :data:`COMMAND_MODULES` to make its commands appear.

Exit codes: 0 success; 1 an unexpected internal error (traceback shown); 2 bad input or a
failed check (one line on stderr naming the file and the problem); 3 a validation target not met
(``validate itk-pair`` / ``validate breathing`` with ``--strict``); 130 interrupted (Ctrl-C);
143 terminated (SIGTERM, which unwinds as Ctrl-C does: every writer removes its partial output).
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass

import typer

from lungdeform import __version__
from lungdeform.errors import LungdeformError
from lungdeform.io.grid import MAX_VOXELS_ENV

from .common import MAX_VOXELS_HELP, Verbosity, set_max_voxels

COMMAND_MODULES = [
    "lungdeform.cli.build",
    "lungdeform.cli.demo",
    "lungdeform.cli.bench",
    "lungdeform.cli.validate_paper",
    "lungdeform.cli.segment",
    "lungdeform.cli.validate_dirlab",
    "lungdeform.cli.export",
    "lungdeform.cli.view",
    "lungdeform.cli.bench_viewer",
    "lungdeform.cli.breathe",
    "lungdeform.cli.validate_breathing",
    "lungdeform.cli.validate_prediction",
    "lungdeform.cli.validate_gating",
    "lungdeform.cli.stream",
    "lungdeform.cli.fit",
    "lungdeform.cli.validate_itk",
    "lungdeform.cli.validate_copd",
    "lungdeform.cli.validate_single_scan",
    "lungdeform.cli.cohort",
    "lungdeform.cli.bench_cohort",
    "lungdeform.cli.synth_cohort",
    "lungdeform.cli.track",
    "lungdeform.cli.dvf",
    "lungdeform.cli.warp",
    "lungdeform.cli.bench_dvf",
    "lungdeform.cli.bench_export",
    "lungdeform.cli.bench_fit",
]


@dataclass(frozen=True)
class Apps:
    root: typer.Typer
    validate: typer.Typer
    bench: typer.Typer


def make_app() -> typer.Typer:
    root = typer.Typer(
        name="lungdeform",
        help="Real-time, physics-based 3-D breathing lung models from CT (Santhanam et al. 2008).",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )
    validate = typer.Typer(help="Validate the model against the paper and real data.", no_args_is_help=True)
    bench = typer.Typer(help="Benchmarks, reported as ratios against a yardstick run alongside.", no_args_is_help=True)
    root.add_typer(validate, name="validate")
    root.add_typer(bench, name="bench")

    def _print_version(value: bool) -> None:
        if value:  # eager: runs before click asks for a command

            typer.echo(__version__)
            raise typer.Exit(0)

    @root.callback()
    def _root(
        ctx: typer.Context,
        version: bool = typer.Option(False, "--version", help="Print the version and exit.", is_eager=True,
                                     callback=_print_version),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show progress even when stderr is not a terminal."),
        max_voxels: str = typer.Option(None, "--max-voxels", help=MAX_VOXELS_HELP),
    ):
        ctx.obj = Verbosity(verbose)  # read by common.progress_enabled, through the context
        set_max_voxels(max_voxels)

    apps = Apps(root, validate, bench)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(apps)
    return root


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; return the exit code (also used by ``python -m lungdeform``)."""

    for stream in (sys.stdout, sys.stderr):  # never crash on "→" or "Δ" under an ASCII locale
        if hasattr(stream, "reconfigure") and (stream.encoding or "").lower().replace("-", "") != "utf8":
            stream.reconfigure(errors="replace")
    app = make_app()
    before = os.environ.get(MAX_VOXELS_ENV)  # --max-voxels sets it for this command (and its workers) only
    try:
        return _run_app(app, argv)
    finally:
        if before is None:
            os.environ.pop(MAX_VOXELS_ENV, None)
        else:
            os.environ[MAX_VOXELS_ENV] = before


def _run_app(app, argv) -> int:
    """Run ``app`` on ``argv``; the exit code of :func:`main`."""
    try:
        # standalone mode: typer itself reports usage errors (exit 2) and Ctrl-C
        with signals_interrupt() as signalled:
            app(args=argv, prog_name="lungdeform")
    except SystemExit as exc:
        if exc.code is None:
            return 0
        if signalled:  # typer turns the KeyboardInterrupt into exit 130 without a word
            return _stopped(signalled[0] == signal.SIGTERM)
        return exc.code if isinstance(exc.code, int) else 1
    except KeyboardInterrupt as exc:
        return _stopped(isinstance(exc, Terminated))
    except LungdeformError as exc:
        typer.echo(f"error: {_one_line(exc)}", err=True)
        return 2
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
        return 2
    except Exception as exc:
        stop = _interruption(exc)
        if stop is None:
            raise
        return _stopped(isinstance(stop, Terminated))  # clean-up code raised while the signal unwound
    return 0


def _stopped(terminated: bool) -> int:
    """Say how the command was stopped (one line on stderr); the exit code of a process killed by
    SIGTERM (143) or SIGINT (130)."""
    typer.echo("terminated" if terminated else "interrupted", err=True)
    return 143 if terminated else 130


def _interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (or :class:`Terminated`) ``exc`` was raised while handling, if any: a
    library's clean-up (zipfile closing a half-written member, say) can raise its own error on the
    way out, which would otherwise hide the signal behind a traceback."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is, so that it unwinds as Ctrl-C does (partial outputs removed)."""


@contextmanager
def signals_interrupt():
    """While the command runs, SIGTERM raises :class:`Terminated` (a KeyboardInterrupt) instead of
    killing the process outright, and Ctrl-C (SIGINT, unless the process was started with it
    ignored) raises KeyboardInterrupt as Python's own handler does. Either one arriving where an
    exception must not be raised (:func:`_no_raise_here`: a callback from compiled code, zipfile
    writing a member) is sent again a little later. The previous handlers are put back after. Only in the main thread (where Python delivers
    signals); elsewhere nothing changes."""
    signalled: list[int] = []  # yielded: the signals that came (SIGTERM, SIGINT)
    if threading.current_thread() is not threading.main_thread():
        yield signalled
        return

    def handler(signum, frame):
        if _no_raise_here(frame):  # an exception there is dropped or breaks clean-up: ask again a little later
            threading.Timer(0.05, os.kill, (os.getpid(), signum)).start()
            return
        signalled.append(signum)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt()
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM does not cut the clean-up short
        raise Terminated()

    handled = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        handled.append(signal.SIGINT)
    previous = {signum: signal.signal(signum, handler) for signum in handled}
    try:
        yield signalled
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)


def _no_raise_here(frame) -> bool:
    """Whether ``frame`` runs where an exception must not be raised: inside a Python callback called
    from compiled code (llvmlite's object cache during a numba compilation), where it cannot
    propagate, or inside :mod:`zipfile` writing a member (numpy's ``savez`` of a model file), whose
    clean-up then fails ("seek of closed file") and hides the signal behind a traceback."""
    while frame is not None:
        name = frame.f_code.co_filename
        if "llvmlite" in name or os.path.basename(name) == "zipfile.py" or f"{os.sep}zipfile{os.sep}" in name:
            return True
        frame = frame.f_back
    return False


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def run() -> None:  # pragma: no cover - console-script shim
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
