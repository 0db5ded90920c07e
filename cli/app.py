"""What the commands share: the typer apps they register on, the stop signals, the common options and helpers."""


from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated, Optional

import typer

from seasynth.service.errors import SeasynthError

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


def stop_command(signum: int, frame) -> None:
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


def stopped_by() -> signal.Signals:
    """The signal that stopped the running command (SIGINT unless SIGTERM or SIGHUP did)."""
    return _stopped_by
