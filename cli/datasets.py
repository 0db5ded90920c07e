"""Dataset commands: generate, reproduce, export, preview, waterfall, calibrate and fetch."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from seasynth.cli.app import (
    FramesOpt,
    HeightOpt,
    Interrupted,
    PlatformOpt,
    QualityOpt,
    SeedOpt,
    WidthOpt,
    app,
    bad_option,
    count_or_auto,
    load_overridden,
    progress,
)
from seasynth.service.errors import OutputError, SeasynthError, SpecError


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
    gpus: Annotated[Optional[str], typer.Option("--gpus", help="Spread the render processes over GPUs, process k "
                                                "on the k-th round robin: auto (every GPU EGL finds; none: the "
                                                "default device), a count N (the first N), or EGL device indices "
                                                "0,1 (one: 1,). Frames are the same on any GPU of one model.")] = None,
    timeline: Annotated[Optional[Path], typer.Option(
        "--timeline", help="With several workers, append each render process's start-up and frame events to this "
        "file as JSON lines (for benchmarks: python -m seasynth.bench.startup_timeline).")] = None,
) -> None:
    """Generate a dataset locally (no servers): image_2/, label_2/, calib/, meta/ and optional outputs. The spec's
    outputs.coco, yolo and mcap are then exported into OUT/export/{format}/ with outputs.split (COCO without
    outputs.instance renders each frame again for its masks)."""
    if resume and overwrite:
        raise SpecError("--resume and --overwrite exclude each other")
    count = count_or_auto(workers, "--workers")
    choice = _gpu_choice(gpus)
    s = load_overridden(spec, frames, seed, width, height, quality)  # before the renderer's imports: fail fast
    if count is None or count > 1:
        from seasynth.worker.local.pool_start import start_early

        start_early()  # its imports overlap the next line's
    from seasynth.worker.local.generate import auto_workers, open_dataset, render_frames
    from seasynth.worker.render.devices import check_devices

    if timeline is not None:  # a file the render processes cannot write would lose their notes silently
        try:
            with timeline.open("a", encoding="utf-8"):
                pass
        except OSError as err:
            raise OutputError(f"{timeline}: cannot write the timeline ({err.strerror or err})") from None

    check_devices(gl, choice)  # a device this machine lacks is refused before OUT is made
    todo = open_dataset(s, out, "resume" if resume else "overwrite" if overwrite else "new")
    if count is None:
        from seasynth.worker.local.capacity import gpus_found

        # EGL's devices are listed in this process: render processes start from the fork server, not from here.
        workers = auto_workers(len(todo), gpus_found(gl, choice))
    else:
        workers = count
    try:
        with progress(len(todo), "frames") as bar:
            task = bar.add_task("render", total=len(todo))
            report = render_frames(s, out, todo, workers=workers, on_frames=lambda n: bar.advance(task, n),
                                   platform=gl, gpus=choice, timeline=timeline)
    except KeyboardInterrupt:
        raise Interrupted(f"{out}: the frames written so far are complete; the same command with --resume "
                          "renders the rest") from None
    typer.echo(
        f"{out}: {report.frames_total} frames ({report.frames_rendered} rendered, "
        f"{report.frames_skipped} already complete) on {report.renderer or 'no renderer needed'}"
    )
    if s.outputs.exports:
        from seasynth.worker.export import export_generated

        try:
            with progress(s.frames * len(s.outputs.exports), "export") as bar:
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
    s = load_overridden(spec, frames, seed, width, height, quality)
    from seasynth.worker.local.generate import reproduce as run

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
    """Convert a local dataset to COCO, YOLO or MCAP (one ROS 2 bag per split), split into train/val/test. COCO's
    masks come from instance/, or are re-rendered (and checked against the dataset's images) when the dataset has
    none."""
    from seasynth.worker.export import FORMATS, parse_split, plan_export, run_export
    from seasynth.worker.export.files import check_export_folder

    if fmt not in FORMATS:
        raise bad_option(ctx, "fmt", f"{fmt!r} is not one of {', '.join(FORMATS)}")
    try:
        fractions = None if split is None else parse_split(split)
    except SeasynthError as err:
        raise bad_option(ctx, "split", str(err)) from None
    check_export_folder(out, fmt)  # before any work or progress bar
    plan = plan_export(dataset, fmt, fractions, partial=partial, distractors=distractors)
    if plan.skipped:
        typer.echo(f"{dataset}: {plan.skipped} incomplete frame(s) skipped (--partial)")
    if plan.renders_masks:
        typer.echo(f"{dataset}: no instance/ (or meta/) outputs: re-rendering each frame for its instance masks, "
                   "checked byte for byte against the dataset's image and labels")
    try:
        with progress(plan.frames, "frames") as bar:
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
    """A contact sheet of the first frames (boxes, depth, instances, FLS fan) and a label summary over every frame."""
    from seasynth.worker.preview.sheet import make_preview, markdown

    with progress(0, "frames") as bar:
        task = bar.add_task("preview", total=None)
        p = make_preview(dataset, out, frames, on_frames=lambda n: bar.advance(task, n),
                         on_total=lambda n: bar.update(task, total=n), tile_width=tile_width)
    typer.echo(markdown(p.summary), nl=False)
    typer.echo(f"{p.sheet}: {p.tiles} of {p.summary.frames} complete frames; summary in {p.table}")


@app.command()
def waterfall(
    dataset: Annotated[Path, typer.Argument(help="A local dataset folder with side-scan rows (sss/).")],
    out: Annotated[Path, typer.Option("--out", help="Waterfall PNG.")],
    labels: Annotated[bool, typer.Option("--labels", help="Draw the targets' boxes from sss_label/.")] = False,
    row_height: Annotated[int, typer.Option("--row-height", min=1, help="Pixels per ping row.")] = 1,
) -> None:
    """The side-scan rows of every frame, stacked in frame order (first on top), with the targets' boxes."""
    from seasynth.worker.preview.waterfall import write_waterfall

    w, path = write_waterfall(dataset, out, row_height, labels)
    typer.echo(f"{path}: {w.rows.shape[0]} pings x {w.rows.shape[1]} bins, {len(w.boxes)} target boxes"
               + ("" if labels else " (not drawn: --labels draws them)"))


def _gpu_choice(text: str | None):
    """--gpus: None (not given: the default device), else the parsed choice."""
    from seasynth.service.gpus import parse_gpus

    if text is None:
        return None
    try:
        return parse_gpus(text)
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="'--gpus'") from None


@app.command()
def calibrate(
    photo: Annotated[Path, typer.Argument(help="Underwater photo: 8-bit sRGB (PNG, JPEG, ...).")],
    depth: Annotated[Optional[Path], typer.Option("--depth", help="Range map of the photo, same size, range along "
                                                  "each pixel's line of sight (not z-depth): 16-bit PNG in mm (0: "
                                                  "none), .npy float metres, or 32-bit float TIFF in metres "
                                                  "(.npy/.tif: NaN none, +inf open water).")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Write the spec water: section here (YAML).")] = None,
    range_spread: Annotated[float, typer.Option("--range-spread", min=0.0, help="Relative half-width of each "
                                                "coefficient's range in the spec, in [0, 1) (0: fixed water).")] = 0.1,
    seed: Annotated[int, typer.Option("--seed", help="Bootstrap seed.")] = 0,
    prior: Annotated[Optional[str], typer.Option("--prior", help="With --depth: jerlov (the default: beta_D from the "
                                                 "Jerlov family and one beta_B/beta_D ratio for all channels, the "
                                                 "water the generator renders; biased off it) or none (each channel "
                                                 "fitted freely).")] = None,
) -> None:
    """Estimate the water (beta_D, beta_B, B_inf with uncertainties) of a real photo, with or without a range map,
    and write it as a spec water: section."""
    from seasynth.service.calibration.io import estimate_files
    from seasynth.service.calibration.output import describe, to_spec_water
    from seasynth.service.errors import CalibrationError

    if not range_spread < 1.0:  # as POST /calibrate takes it
        raise typer.BadParameter(f"{range_spread} is not below 1", param_hint="'--range-spread'")

    def read(path: Path) -> bytes:
        try:
            return path.read_bytes()
        except OSError as err:
            raise CalibrationError(f"{path}: cannot read ({err.strerror or err})") from None

    estimate = estimate_files(read(photo), str(photo), None if depth is None else read(depth), str(depth), seed=seed,
                              prior=prior)
    water = to_spec_water(estimate, spread=range_spread)
    typer.echo(describe(estimate))
    import yaml

    text = yaml.safe_dump({"water": water}, sort_keys=False)
    if out is None:
        typer.echo(text, nl=False)
        return
    try:
        def shown(name: str) -> str:  # a file name with a line break must not end the YAML comment
            return "".join(ch if ch.isprintable() else "?" for ch in name)

        out.write_text(f"# seasynth calibrate {shown(photo.name)}" + (f" --depth {shown(depth.name)}" if depth else "")
                       + "\n"
                       + "".join(f"# {n}\n" for n in estimate.notes) + text)
    except OSError as err:
        raise CalibrationError(f"{out}: cannot write ({err.strerror or err})") from None
    typer.echo(f"{out}: water section written")


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
    from seasynth.service.fetch import fetch_dataset
    from seasynth.service.settings import Settings
    from seasynth.service.spec.outputs import EXPORT_FORMATS

    merger = None
    if fmt is not None:
        if fmt not in EXPORT_FORMATS:
            raise bad_option(ctx, "fmt", f"{fmt!r} is not one of {', '.join(EXPORT_FORMATS)}")
        from seasynth.worker.export.merge import PartMerger

        merger = PartMerger(fmt)
    s = Settings()
    r = fetch_dataset(api or s.api_url, dataset_id, out, api_key=api_key or s.api_key, parallel=parallel,
                      partial=partial, merger=merger)
    what = "shards" if fmt is None else f"{fmt} parts"
    typer.echo(f"{out}: {r.shards_total} {what} ({r.shards_fetched} fetched, {r.shards_skipped} already "
               f"complete), {r.files} files written")
