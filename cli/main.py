"""The `seasynth` entry point: the commands registered (by importing their modules) and every error mapped to one
clear line and an exit code."""

from __future__ import annotations

import signal
import sys
import threading
from typing import NoReturn

import typer

from seasynth.cli import bench, datasets, servers  # noqa: F401 (importing them registers their commands)
from seasynth.cli.app import STOP_SIGNALS, Interrupted, app, stop_command, stopped_by
from seasynth.service.errors import SeasynthError, SpecError


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
                signal.signal(sig, stop_command)
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
    signum = stopped_by()
    what = "interrupted" if signum == signal.SIGINT else f"stopped by {signum.name}"
    typer.echo(f"{what}: {detail}" if detail else what, err=True)
    sys.exit(128 + int(signum))


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
