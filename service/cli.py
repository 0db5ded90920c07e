"""The `seasynth` command: the composition root. Each command imports its adapter when it runs, so `serve`
never loads OpenGL and `generate` never loads the web stack."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, NoReturn, Optional

import typer

from service.errors import SeasynthError, SpecError

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Labelled synthetic underwater images.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: throughput and accuracy tables.")
app.add_typer(bench_app, name="bench")


class Interrupted(Exception):
    """Ctrl-C stopped a command; the message says what it leaves behind. `main` prints it and exits 130."""


FramesOpt = Annotated[Optional[int], typer.Option("--frames", help="Override the spec's frame count.")]
SeedOpt = Annotated[Optional[int], typer.Option("--seed", help="Override the spec's dataset seed.")]
WidthOpt = Annotated[Optional[int], typer.Option("--width", help="Override camera.width.")]
HeightOpt = Annotated[Optional[int], typer.Option("--height", help="Override camera.height.")]
QualityOpt = Annotated[Optional[str], typer.Option("--quality", help="Override the quality preset.")]
PlatformOpt = Annotated[str, typer.Option("--gl", help="Headless GL platform: egl or osmesa.")]


def _load(spec_path: Path, frames, seed, width, height, quality=None):
    from service.spec import load_spec

    overrides = {"frames": frames, "seed": seed, "camera.width": width, "camera.height": height, "quality": quality}
    return load_spec(spec_path, overrides)


def _progress(total: int, description: str):
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


@app.command()
def generate(
    spec: Annotated[Path, typer.Argument(help="Dataset spec (.yaml, .yml or .json).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder (KITTI layout).")],
    frames: FramesOpt = None,
    seed: SeedOpt = None,
    width: WidthOpt = None,
    height: HeightOpt = None,
    quality: QualityOpt = None,
    workers: Annotated[str, typer.Option("--workers", help="Local render processes: a count, or auto (one per "
                                         "usable CPU core, at most one per frame to render).")] = "1",
    resume: Annotated[bool, typer.Option("--resume", help="Complete a partly written dataset.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the dataset in OUT.")] = False,
    gl: PlatformOpt = "egl",
) -> None:
    """Generate a dataset locally (no servers): image_2/, label_2/, calib/, meta/ and optional outputs. The spec's
    outputs.coco, yolo and mcap are then exported into OUT/export/{format}/ with outputs.split (COCO without
    outputs.instance renders each frame again for its masks)."""
    if resume and overwrite:
        raise SpecError("--resume and --overwrite exclude each other")
    count = _worker_count(workers)
    s = _load(spec, frames, seed, width, height, quality)  # before the renderer's imports: bad specs fail fast
    from worker.generate import auto_workers, open_dataset, render_frames

    todo = open_dataset(s, out, "resume" if resume else "overwrite" if overwrite else "new")
    workers = auto_workers(len(todo)) if count is None else count
    try:
        with _progress(len(todo), "frames") as bar:
            task = bar.add_task("render", total=len(todo))
            report = render_frames(s, out, todo, workers=workers, on_frames=lambda n: bar.advance(task, n),
                                   platform=gl)
    except KeyboardInterrupt:
        raise Interrupted(f"{out}: the frames written so far are complete; the same command with --resume "
                          "renders the rest") from None
    typer.echo(
        f"{out}: {report.frames_total} frames ({report.frames_rendered} rendered, "
        f"{report.frames_skipped} already complete) on {report.renderer or 'no renderer needed'}"
    )
    if s.outputs.exports:
        from worker.export import export_generated

        try:
            with _progress(s.frames * len(s.outputs.exports), "export") as bar:
                task = bar.add_task("export", total=s.frames * len(s.outputs.exports))
                exports = export_generated(out, on_frames=lambda n: bar.advance(task, n), platform=gl)
        except KeyboardInterrupt:
            raise Interrupted(f"{out}: the frames are complete, an export is not; the same command with --resume "
                              "exports again") from None
        for r in exports:
            typer.echo(f"{r.out}: {r.format} export ({', '.join(f'{k} {v}' for k, v in r.frames.items())})")


@app.command()
def reproduce(
    spec: Annotated[Path, typer.Argument(help="The dataset's spec file.")],
    frame: Annotated[int, typer.Option("--frame", min=0, help="Frame index.")],
    out: Annotated[Path, typer.Option("--out", help="Folder to write the frame's files into.")],
    frames: FramesOpt = None,
    seed: SeedOpt = None,
    width: WidthOpt = None,
    height: HeightOpt = None,
    quality: QualityOpt = None,
    gl: PlatformOpt = "egl",
) -> None:
    """Re-render one frame from (spec, seed, frame index): byte-identical to the frame `generate` wrote."""
    s = _load(spec, frames, seed, width, height, quality)
    from worker.generate import reproduce as run

    for rel in run(s, frame, out, platform=gl):
        typer.echo(str(out / rel))


@app.command()
def export(
    ctx: typer.Context,
    dataset: Annotated[Path, typer.Argument(help="A local dataset folder (from generate or fetch).")],
    fmt: Annotated[str, typer.Option("--format", help="coco, yolo (Ultralytics layout) or mcap (ROS 2 bags; "
                                     "needs the export extra).")],
    out: Annotated[Path, typer.Option("--out", help="Export folder: new, empty, or an earlier export of the "
                                      "same format (replaced).")],
    split: Annotated[Optional[str], typer.Option("--split", help="train,val,test fractions (>= 0, summing to 1; "
                                                 "default: the spec's outputs.split, 0.8,0.1,0.1 unless set); a "
                                                 "frame's split is drawn from (dataset seed, frame index) alone.")]
    = None,
    partial: Annotated[bool, typer.Option("--partial", help="Export the complete frames of an incomplete "
                                          "dataset.")] = False,
    distractors: Annotated[bool, typer.Option("--distractors", help="Also label visible distractors "
                                              "(class 'distractor').")] = False,
    gl: PlatformOpt = "egl",
) -> None:
    """Convert a local dataset to COCO or YOLO, split into train/val/test. COCO's masks come from instance/, or
    are re-rendered (and checked against the dataset's images) when the dataset has none."""
    from worker.export import FORMATS, parse_split, plan_export, run_export

    if fmt not in FORMATS:
        raise _bad_option(ctx, "fmt", f"{fmt!r} is not one of {', '.join(FORMATS)}")
    try:
        fractions = None if split is None else parse_split(split)
    except SeasynthError as err:
        raise _bad_option(ctx, "split", str(err)) from None
    plan = plan_export(dataset, fmt, fractions, partial=partial, distractors=distractors)
    if plan.skipped:
        typer.echo(f"{dataset}: {plan.skipped} incomplete frame(s) skipped (--partial)")
    if plan.renders_masks:
        typer.echo(f"{dataset}: no instance/ (or meta/) outputs: re-rendering each frame for its instance masks, "
                   "checked byte for byte against the dataset's image and labels")
    try:
        with _progress(plan.frames, "frames") as bar:
            task = bar.add_task("export", total=plan.frames)
            r = run_export(plan, out, on_frames=lambda n: bar.advance(task, n), platform=gl)
    except KeyboardInterrupt:
        raise Interrupted(f"{out}: unfinished export (seasynth-export.json says incomplete); the same command "
                          "completes it") from None
    per_split = ", ".join(f"{k} {v}" for k, v in r.frames.items())
    typer.echo(f"{out}: {fmt} export of {sum(r.frames.values())} frames ({per_split}), "
               f"{r.skipped} incomplete frame(s) skipped")


@app.command()
def preview(
    dataset: Annotated[Path, typer.Argument(help="A local dataset folder (from generate or fetch).")],
    out: Annotated[Path, typer.Option("--out", help="Contact sheet PNG; the summary table goes next to it "
                                      "(.md).")],
    frames: Annotated[int, typer.Option("--frames", min=1, help="Frames on the sheet (the first complete "
                                        "ones); the summary covers all.")] = 12,
    tile_width: Annotated[Optional[int], typer.Option("--tile-width", min=1, help="Widest image panel, px "
                                                      "(default 320): wider frames are scaled down, boxes with "
                                                      "them.")] = None,
) -> None:
    """A contact sheet of the first frames (boxes, depth, instances) and a label summary over every frame."""
    from worker.preview import make_preview, markdown

    with _progress(0, "frames") as bar:
        task = bar.add_task("preview", total=None)
        p = make_preview(dataset, out, frames, on_frames=lambda n: bar.advance(task, n),
                         on_total=lambda n: bar.update(task, total=n), tile_width=tile_width)
    typer.echo(markdown(p.summary), nl=False)
    typer.echo(f"{p.sheet}: {p.tiles} of {p.summary.frames} complete frames; summary in {p.table}")


def _worker_count(text: str) -> int | None:
    """--workers: None for auto, else a count >= 1."""
    if text.strip().lower() == "auto":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise typer.BadParameter(f"{text!r}: give a count >= 1 or auto", param_hint="'--workers'")
    return n


def _bad_option(ctx: typer.Context, name: str, message: str) -> typer.BadParameter:
    """A usage error naming the option of parameter `name` as click names it ("Invalid value for '--split'")."""
    param = next(p for p in ctx.command.params if p.name == name)
    return typer.BadParameter(message, ctx=ctx, param=param)


@bench_app.command("throughput")
def bench_throughput(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    frames: Annotated[int, typer.Option("--frames", min=5)] = 50,
    width: Annotated[int, typer.Option("--width")] = 640,
    height: Annotated[int, typer.Option("--height")] = 480,
    out: Annotated[Optional[Path], typer.Option("--out", help="Also write the table and JSON here.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """Per-stage times, steady-state seconds per frame, and the ratio to stock pyrender, in one run."""
    from bench.throughput import run

    run(spec, frames=frames, width=width, height=height, out=out, platform=gl)


@bench_app.command("scale")
def bench_scale(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    resolution: Annotated[Optional[list[str]], typer.Option("--resolution", help="WIDTHxHEIGHT (repeatable).")] = None,
    workers: Annotated[str, typer.Option("--workers", help="Comma-separated worker counts.")] = "1,2",
    frames_per_worker: Annotated[int, typer.Option("--frames-per-worker", min=4)] = 20,
    preset: Annotated[str, typer.Option("--preset")] = "default",
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for scale.json, .md and .png.")] = None,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """Frames per second against worker processes and resolution through generate, with CPU and GPU utilisation."""
    from bench.scale import run

    try:
        sizes = [tuple(int(v) for v in r.lower().split("x")) for r in (resolution or ["640x480"])]
        counts = [int(v) for v in workers.split(",")]
    except ValueError:
        raise typer.BadParameter("--resolution takes WIDTHxHEIGHT and --workers comma-separated integers") from None
    if any(len(s) != 2 or min(s) < 1 for s in sizes) or min(counts) < 1:
        raise typer.BadParameter("--resolution takes WIDTHxHEIGHT and --workers counts >= 1")
    run(spec, resolutions=sizes, workers=counts, frames_per_worker=frames_per_worker, preset=preset, out=out,
        platform=gl, machine=machine)


@bench_app.command("accuracy")
def bench_accuracy(
    out: Annotated[Path, typer.Option("--out", help="Folder for accuracy.json, .md and .png.")],
    scene: Annotated[Optional[list[str]], typer.Option("--scene", help="Scene name (repeatable).")] = None,
    preset: Annotated[Optional[list[str]], typer.Option("--preset", help="Preset name (repeatable).")] = None,
    repeats: Annotated[int, typer.Option("--repeats", min=5)] = 5,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """Each preset against a 16-sample float64 reference on pinned scenes: time, PSNR, errors."""
    from bench.accuracy import run

    run(out, scenes=scene, presets=preset, repeats=repeats, machine=machine, platform=gl)


@bench_app.command("fidelity")
def bench_fidelity(
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for fidelity.json, .md and .png.")] = None,
    config: Annotated[
        Optional[list[str]],
        typer.Option("--config", help="A pinned configuration's name, or NAME=WATER:LIGHT[@DEPTH] (repeatable)."),
    ] = None,
    spp: Annotated[int, typer.Option("--spp", min=1, help="Path-traced samples per pixel of each half of a "
                                     "reference rendered here (when none is stored).")] = 1024,
    references: Annotated[Path, typer.Option(
        "--references", help="Stored references (NAME.ref.npz), used where they match the scene.",
    )] = Path("bench/results/cpu/fidelity-references"),
    export_scenes: Annotated[Optional[Path], typer.Option("--export-scenes", help="Only write each configuration's "
                             "path-tracer scene (NAME.scene.npz) here, for python -m bench.reference.")] = None,
    timing_spp: Annotated[int, typer.Option("--timing-spp", min=1, help="Samples per pixel of the path tracer's "
                                            "timed render on this machine.")] = 64,
    repeats: Annotated[int, typer.Option("--repeats", min=1)] = 5,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """seasynth's frames against a volumetric path tracer of the same scene: PSNR, MAE, time, per term."""
    from bench.fidelity import CONFIGS, export_scenes as export, parse_config, run

    chosen: dict[str, str] = {}
    for c in config or list(CONFIGS):
        name, _, text = c.partition("=")
        if not text and name not in CONFIGS:
            raise typer.BadParameter(f"unknown configuration {name!r}; pinned: {', '.join(CONFIGS)}",
                                     param_hint="--config")
        chosen[name] = text or CONFIGS[name]
        parse_config(chosen[name])
    if export_scenes is not None:
        for path in export(export_scenes, configs=chosen, platform=gl):
            typer.echo(str(path))
        return
    if out is None:
        raise typer.BadParameter("give --out (or --export-scenes)", param_hint="--out")
    run(out, configs=chosen, spp=spp, repeats=repeats, machine=machine, platform=gl, references=references,
        timing_spp=timing_spp)


@app.command()
def serve(
    host: Annotated[str, typer.Option("--host", help="Interface to bind.")] = "0.0.0.0",
    port: Annotated[int, typer.Option("--port", min=1, max=65535, help="TCP port.")] = 8000,
    processes: Annotated[int, typer.Option("--workers", min=1, help="uvicorn worker processes.")] = 1,
) -> None:
    """Run the HTTP API (settings from SEASYNTH_* and AWS_* environment variables)."""
    from api.main import serve as run
    from service.settings import Settings

    run(Settings(), host=host, port=port, workers=processes)


@app.command()
def worker(
    concurrency: Annotated[int, typer.Option("--concurrency", "-c", min=1, help="Render processes.")] = 1,
    queues: Annotated[str, typer.Option("--queues", "-Q", help="shards, frames, or both (comma-separated).")]
    = "shards,frames",
    loglevel: Annotated[str, typer.Option("--loglevel", help="Celery log level.")] = "INFO",
) -> None:
    """Run a render worker (Celery, prefork) on this code version's queues; several may share a host."""
    from service.settings import Settings
    from worker.celery_app import run_worker

    run_worker(Settings(), concurrency, [q.strip() for q in queues.split(",") if q.strip()], loglevel)


RECONCILE_EVERY_S = (0.1, 86400.0)  # a round at most ten times a second (Redis) and at least once a day


def _positive_seconds(value: Optional[float]) -> Optional[float]:
    lo, hi = RECONCILE_EVERY_S
    if value is not None and not (lo <= value <= hi):  # NaN fails both comparisons
        raise typer.BadParameter(f"must be a number of seconds from {lo:g} to {hi:g}, got {value:g}")
    return value


@app.command()
def reconcile(
    ctx: typer.Context,
    dataset_ids: Annotated[
        Optional[list[str]], typer.Argument(help="Datasets to sweep now (default: every stalled one).")
    ] = None,
    every: Annotated[
        Optional[float],
        typer.Option("--every", metavar="SECONDS", callback=_positive_seconds,
                     help="Keep running: a round every SECONDS until SIGTERM or Ctrl-C (no DATASET_IDs then).")
    ] = None,
) -> None:
    """Republish lost shards: of the given datasets now, or of every live dataset that has stalled (nothing started,
    committed or failed for SEASYNTH_STALL_TIMEOUT_S and nothing running). Safe to run at any time, e.g. from cron.
    With --every it keeps running until SIGTERM: each round sweeps every stalled dataset, has the manifests that
    could not be written written, and touches seasynth-reconciler.alive in the temp folder for health checks."""
    if every is not None and dataset_ids:
        ctx.fail("--every and DATASET_IDs exclude each other: each round of --every sweeps every stalled dataset")
    from api.deps import open_services
    from api.operations import sweep_all
    from service.settings import Settings

    services = open_services(Settings())
    try:
        if every is not None:
            from service.queues import run_reconciler

            run_reconciler(services, every, lambda: sweep_all(services), echo=typer.echo)
            return
        swept = sweep_all(services, dataset_ids)
    finally:
        services.close()
    for dataset_id in swept:
        typer.echo(f"{dataset_id}: pending shards sent to a worker to publish again")
    typer.echo(f"{len(swept)} dataset(s) swept")


@app.command()
def fetch(
    ctx: typer.Context,
    dataset_id: Annotated[str, typer.Argument(help="Dataset id (from POST /datasets).")],
    out: Annotated[Path, typer.Option("--out", help="Folder to assemble the KITTI tree in.")],
    api: Annotated[Optional[str], typer.Option("--api", help="API URL [env SEASYNTH_API_URL].")] = None,
    api_key: Annotated[Optional[str], typer.Option("--api-key", help="API key [env SEASYNTH_API_KEY].")] = None,
    parallel: Annotated[int, typer.Option("--parallel", min=1, help="Shards downloaded at once.")] = 4,
    partial: Annotated[bool, typer.Option("--partial", help="Fetch the shards committed so far.")] = False,
    fmt: Annotated[Optional[str], typer.Option("--format", help="coco, yolo or mcap: merge the shards' parts of "
                                               "that format (the dataset needs outputs.FORMAT) into one export in "
                                               "OUT, as `seasynth export` writes it; MCAP: one bag per shard and "
                                               "split, SPLIT-SHARD.mcap.")] = None,
) -> None:
    """Download a dataset's shards, verify sha256, resume after interruption, and assemble one KITTI tree (or, with
    --format, one export of that format)."""
    from service.fetch import fetch_dataset
    from service.settings import Settings
    from service.spec import EXPORT_FORMATS

    merger = None
    if fmt is not None:
        if fmt not in EXPORT_FORMATS:
            raise _bad_option(ctx, "fmt", f"{fmt!r} is not one of {', '.join(EXPORT_FORMATS)}")
        from worker.export.merge import PartMerger

        merger = PartMerger(fmt)
    s = Settings()
    r = fetch_dataset(api or s.api_url, dataset_id, out, api_key=api_key or s.api_key, parallel=parallel,
                      partial=partial, merger=merger)
    what = "shards" if fmt is None else f"{fmt} parts"
    typer.echo(f"{out}: {r.shards_total} {what} ({r.shards_fetched} fetched, {r.shards_skipped} already "
               f"complete), {r.files} files written")


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


def _interrupted(detail: str | None = None) -> NoReturn:
    """One line on stderr, exit 130 (128 + SIGINT) as shells expect of Ctrl-C."""
    typer.echo(f"interrupted: {detail}" if detail else "interrupted", err=True)
    sys.exit(130)


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


if __name__ == "__main__":
    main()
