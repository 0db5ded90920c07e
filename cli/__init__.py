"""The `seasynth` command: the composition root. Each command imports its adapter (worker/, api/, bench/) when
it runs, so `serve` never loads OpenGL and `generate` never loads the web stack; nothing in the domain imports
this package. Commands live by kind: datasets.py (generate .. fetch), servers.py (serve, worker, playground,
reconcile), bench.py (`seasynth bench ...`)."""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, NoReturn, Optional

import typer

from seasynth.service.errors import SeasynthError, SpecError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Labelled synthetic underwater images.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: throughput and accuracy tables.")
app.add_typer(bench_app, name="bench")


class Interrupted(Exception):
    """Ctrl-C (or SIGTERM, SIGHUP) stopped a command; the message says what it leaves behind. `main` prints it and
    exits 128 + the signal's number."""


# SIGTERM (docker stop, timeout, a batch scheduler) and SIGHUP (a closed terminal) stop a command as Ctrl-C does: the
# same unwinding (render processes stopped, temporary files and folders removed, the record left incomplete),
# instead of the interpreter dying where it stands. Servers (serve, worker) install their own handlers on start.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
_stopped_by = signal.SIGINT


def _stop(signum: int, frame) -> None:
    global _stopped_by
    _stopped_by = signal.Signals(signum)
    raise KeyboardInterrupt


FramesOpt = Annotated[Optional[int], typer.Option("--frames", help="Override the spec's frame count.")]
SeedOpt = Annotated[Optional[int], typer.Option("--seed", help="Override the spec's dataset seed.")]
WidthOpt = Annotated[Optional[int], typer.Option("--width", help="Override camera.width.")]
HeightOpt = Annotated[Optional[int], typer.Option("--height", help="Override camera.height.")]
QualityOpt = Annotated[Optional[str], typer.Option("--quality", help="Override the quality preset.")]


def _platform(value: str) -> str:
    """--gl: refused as a usage error (exit 2) before the command does anything."""
    from seasynth.service.gpus import parse_platform

    try:
        parse_platform(value)
    except SeasynthError as err:
        raise typer.BadParameter(str(err), param_hint="'--gl'") from None
    return value


PlatformOpt = Annotated[str, typer.Option("--gl", help="Headless GL platform: egl, egl:N (EGL device N) or osmesa.",
                                          callback=_platform)]


def load_overridden(spec_path: Path, frames, seed, width, height, quality=None):
    from seasynth.service.spec.dataset import load_spec

    overrides = {"frames": frames, "seed": seed, "camera.width": width, "camera.height": height, "quality": quality}
    return load_spec(spec_path, overrides)


def progress(total: int, description: str):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    class FramesPerSecond(TextColumn):
        def __init__(self) -> None:
            super().__init__("")

        def render(self, task):  # noqa: D102 (rich's column API)
            speed = task.finished_speed or task.speed
            from rich.text import Text

            return Text(f"{speed:.2f} frames/s" if speed else "-- frames/s")

    return Progress(
        TextColumn(description),
        BarColumn(),
        MofNCompleteColumn(),
        FramesPerSecond(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        transient=False,
    )


def count_or_auto(text: str, option: str) -> int | None:
    """A process count option (--workers, --concurrency): None for auto, else a count >= 1."""
    if text.strip().lower() == "auto":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise typer.BadParameter(f"{text!r}: give a count >= 1 or auto", param_hint=f"'{option}'")
    return n


def bad_option(ctx: typer.Context, name: str, message: str) -> typer.BadParameter:
    """A usage error naming the option of parameter `name` as click names it ("Invalid value for '--split'")."""
    param = next(p for p in ctx.command.params if p.name == name)
    return typer.BadParameter(message, ctx=ctx, param=param)


def _cli_exceptions() -> tuple[tuple[type, ...], tuple[type, ...], tuple[type, ...]]:
    """(Exit, Abort, usage/click error) classes, of typer and of the click package where installed.

    typer 0.29 raises its bundled click's exceptions (all `typer.TyperException`s), which the `click`
    package's classes never match; older typers raise click's own.
    """
    exits, aborts, errors = [typer.Exit], [typer.Abort], [typer.TyperException]
    try:
        import click
    except ImportError:
        pass
    else:
        exits.append(click.exceptions.Exit)
        aborts.append(click.exceptions.Abort)
        errors.append(click.ClickException)
    return tuple(exits), tuple(aborts), tuple(errors)


def main() -> None:
    """Entry point: domain errors become one clear line and an exit code (2 for an invalid spec or usage)."""
    exits, aborts, usage_errors = _cli_exceptions()
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            if signal.getsignal(sig) is signal.SIG_DFL:  # one a parent set to SIG_IGN (nohup) stays ignored
                signal.signal(sig, _stop)
    try:
        code = app(standalone_mode=False, prog_name="seasynth")
    except Interrupted as err:
        _interrupted(str(err))
    except SpecError as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(2)
    except SeasynthError as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(1)
    except ModuleNotFoundError as err:  # a command's adapter needs an extra this install lacks
        typer.echo(f"error: this command needs the Python package {err.name!r}, which is not installed"
                   f"{_extra_hint(err.name)}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        _interrupted()
    except exits as err:
        sys.exit(err.exit_code)
    except aborts:  # what click (older typers) raises for Ctrl-C, and for end of input at a prompt
        _interrupted()
    except usage_errors as err:
        _show_usage_error(err)
        sys.exit(err.exit_code)
    # Outside standalone mode typer returns an Exit's code, and it turns Ctrl-C into Exit(130).
    if code == 130:
        _interrupted()
    if isinstance(code, int) and code:
        sys.exit(code)


# Top-level modules of each extra in pyproject.toml: where a missing one comes from.
EXTRA_OF = {"fastapi": "api", "uvicorn": "api", "multipart": "api", "pyrender": "worker", "trimesh": "worker",
            "OpenGL": "worker", "celery": "worker", "imagecodecs": "worker", "scipy": "worker", "mcap": "export",
            "mcap_ros2": "export", "matplotlib": "bench", "mitsuba": "bench", "selenium": "test"}


def _extra_hint(module: str | None) -> str:
    extra = EXTRA_OF.get((module or "").split(".")[0])
    if extra is None:
        return ""
    return f" (the {extra!r} extra: pip install -c constraints.txt -e '.[{extra}]', or bash .ci/setup for all)"


def _interrupted(detail: str | None = None) -> NoReturn:
    """One line on stderr, exit 128 + the signal's number as shells expect: 130 for Ctrl-C, 143 for SIGTERM."""
    what = "interrupted" if _stopped_by == signal.SIGINT else f"stopped by {_stopped_by.name}"
    typer.echo(f"{what}: {detail}" if detail else what, err=True)
    sys.exit(128 + int(_stopped_by))


def _show_usage_error(err: Exception) -> None:
    """Print a usage error as click does: the usage line, a hint and `Error: ...`, on stderr."""
    ctx = getattr(err, "ctx", None)
    if type(err).__name__ == "NoArgsIsHelpError" and ctx is not None and not err.format_message():
        # typer's rich help has already gone to stdout; say on stderr what was wrong.
        typer.echo(f"{ctx.get_usage()}\nTry '{ctx.command_path} --help' for help.\n\nError: Missing command.",
                   err=True)
    elif hasattr(err, "show"):
        err.show()
    else:  # a bare TyperException has no `show` of its own
        typer.echo(f"Error: {err}", err=True)


# The commands, registered on `app` and `bench_app` by importing their modules (after both exist).
from seasynth.cli import bench, datasets, servers  # noqa: E402,F401
