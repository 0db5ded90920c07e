"""`seasynth bench ...`: each benchmark writes its tables where bench/README.md says."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional, get_args

import typer

from seasynth.cli.app import PlatformOpt, bench_app


@bench_app.command("throughput")
def bench_throughput(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    frames: Annotated[int, typer.Option("--frames", min=5)] = 50,
    width: Annotated[int, typer.Option("--width")] = 640,
    height: Annotated[int, typer.Option("--height")] = 480,
    out: Annotated[Optional[Path], typer.Option("--out", help="Also write the table and JSON here.")] = None,
    preset: Annotated[str, typer.Option("--preset", help="Quality preset of every frame timed.")] = "default",
    gl: PlatformOpt = "egl",
) -> None:
    """Per-stage times, steady-state seconds per frame, and the ratio to stock pyrender, in one run."""
    from seasynth.bench.throughput import run
    from seasynth.service.spec.dataset import Quality

    if preset not in get_args(Quality):
        raise typer.BadParameter(f"{preset!r}: give one of {', '.join(get_args(Quality))}", param_hint="'--preset'")
    run(spec, frames=frames, width=width, height=height, out=out, platform=gl, preset=preset)


@bench_app.command("playground")
def bench_playground(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    frames: Annotated[int, typer.Option("--frames", min=2, help="Frame indices per row.")] = 12,
    out: Annotated[Path, typer.Option("--out", help="Folder for playground.json and .md.")] = Path("bench/results/cpu"),
    gl: PlatformOpt = "egl",
) -> None:
    """Preview latency of `seasynth playground` over HTTP, per view set, and the strip."""
    from seasynth.bench.playground import run

    run(spec, out, frames=frames, platform=gl)


@bench_app.command("scale")
def bench_scale(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    resolution: Annotated[Optional[list[str]], typer.Option("--resolution", help="WIDTHxHEIGHT (repeatable).")] = None,
    workers: Annotated[str, typer.Option("--workers", help="Comma-separated worker counts.")] = "1,2",
    frames_per_worker: Annotated[int, typer.Option("--frames-per-worker", min=4)] = 20,
    preset: Annotated[str, typer.Option("--preset")] = "default",
    mode: Annotated[str, typer.Option("--mode", help="Comma-separated: cli (local generate), service (redis-server, "
                                      "an S3 server, the API and a Celery worker on this machine).")] = "cli",
    gpus: Annotated[Optional[str], typer.Option("--gpus", help="Comma-separated GPU counts: a row each, its workers "
                                                "spread over the first N GPUs. Default: EGL's default device.")] = None,
    storage: Annotated[str, typer.Option("--service-storage", help="Object store of mode service: s3 (moto_server "
                                         "on loopback) or local (a folder).")] = "s3",
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for scale.json, .md and .png.")] = None,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """Frames per second against worker processes, GPUs and resolution through generate and through the service,
    with CPU and GPU utilisation."""
    from seasynth.bench.scale import run

    sizes = [_size(r) for r in (resolution or ["640x480"])]
    modes = tuple(m.strip() for m in mode.split(","))
    if not modes or set(modes) - {"cli", "service"}:
        raise typer.BadParameter(f"{mode!r}: give cli, service or cli,service", param_hint="'--mode'")
    if storage not in ("s3", "local"):
        raise typer.BadParameter(f"{storage!r}: give s3 or local", param_hint="'--service-storage'")
    run(spec, resolutions=sizes, workers=_ints(workers, ",", "--workers", "counts"), frames_per_worker=frames_per_worker,
        preset=preset, out=out, platform=gl, machine=machine, modes=modes,
        gpu_counts=None if gpus is None else _ints(gpus, ",", "--gpus", "counts"), storage=storage)


def _size(text: str) -> tuple[int, int]:
    """--resolution's WIDTHxHEIGHT, each side within what the spec's camera takes; a usage error otherwise."""
    from seasynth.service.spec.scene import MAX_SIDE, MIN_SIDE

    size = _ints(text.lower(), "x", "--resolution", "WIDTHxHEIGHT")
    if len(size) != 2:
        raise typer.BadParameter(f"{text!r}: give WIDTHxHEIGHT, e.g. 1920x1080", param_hint="'--resolution'")
    if not all(MIN_SIDE <= side <= MAX_SIDE for side in size):
        raise typer.BadParameter(f"{text!r}: each side must be {MIN_SIDE}..{MAX_SIDE} pixels",
                                 param_hint="'--resolution'")
    return size[0], size[1]


def _ints(text: str, sep: str, option: str, what: str) -> list[int]:
    """The integers >= 1 of `text` split at `sep`; a usage error naming `option` otherwise."""
    try:
        values = [int(v) for v in text.split(sep)]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise typer.BadParameter(f"{text!r}: give {what} of integers >= 1 separated by {sep!r}",
                                 param_hint=f"'{option}'")
    return values


@bench_app.command("load")
def bench_load(
    rate: Annotated[float, typer.Option("--rate", min=1, help="Status reads and lists offered per second.")] = 200,
    duration: Annotated[float, typer.Option("--duration", min=1, help="Seconds of load.")] = 20,
    posts: Annotated[int, typer.Option("--posts", min=1, help="POST /datasets sent one after another first.")] = 50,
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for load.json and load.md.")] = None,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
) -> None:
    """API latency under status reads and lists while a dataset renders, POST /datasets throughput, /metrics."""
    from seasynth.bench.load import run

    run(rate=rate, duration_s=duration, posts=posts, out=out, machine=machine)


@bench_app.command("accuracy")
def bench_accuracy(
    out: Annotated[Path, typer.Option("--out", help="Folder for accuracy.json, .md and .png.")],
    scene: Annotated[Optional[list[str]], typer.Option("--scene", help="Scene name (repeatable).")] = None,
    preset: Annotated[Optional[list[str]], typer.Option("--preset", help="Preset name (repeatable).")] = None,
    repeats: Annotated[int, typer.Option("--repeats", min=5)] = 5,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
    jpeg: Annotated[Optional[list[int]], typer.Option(
        "--jpeg", min=1, max=100, help="Also `default` with outputs.image_format jpeg at this quality "
        "(repeatable): what JPEG costs against the reference, timed in turns with the presets.")] = None,
) -> None:
    """Each preset against a 16-sample float64 reference on pinned scenes: time, PSNR, errors."""
    from seasynth.bench.accuracy import run

    run(out, scenes=scene, presets=preset, repeats=repeats, machine=machine, platform=gl, jpeg=tuple(jpeg or ()))


@bench_app.command("fidelity")
def bench_fidelity(
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for fidelity.json, .md and .png.")] = None,
    config: Annotated[
        Optional[list[str]],
        typer.Option("--config", help="A pinned configuration's name, or NAME='WATER:LIGHT[@DEPTH] [textured] [long]' "
                    "(repeatable; default: the near-view table's)."),
    ] = None,
    spp: Annotated[int, typer.Option("--spp", min=1, help="Path-traced samples per pixel of each half of a "
                                     "reference rendered here (when none is stored).")] = 1024,
    references: Annotated[Path, typer.Option(
        "--references", help="Stored references (NAME.ref.npz), used where they match the scene.",
    )] = Path("bench/results/cpu/fidelity-references"),
    export_scenes: Annotated[Optional[Path], typer.Option("--export-scenes", help="Only write each configuration's "
                             "path-tracer scene (NAME.scene.npz) here, for python -m bench.reference.")] = None,
    timing_spp: Annotated[int, typer.Option("--timing-spp", min=1, help="Samples per pixel of the shorter of the "
                                            "path tracer's two timed renders on this machine (the other has 4x; "
                                            "a warm-up of this many comes first).")] = 64,
    repeats: Annotated[int, typer.Option("--repeats", min=1)] = 5,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    resolution: Annotated[str, typer.Option("--resolution", help="WIDTHxHEIGHT of the frames and references "
                                            "(other than the table's 320x240: references NAME-WxH.ref.npz).")]
    = "320x240",
    gl: PlatformOpt = "egl",
    forward_scatter: Annotated[bool, typer.Option("--forward-scatter", help="One more row per configuration: "
                                                  "`default` with the forward-scatter blur (+forward_scatter).")]
    = False,
) -> None:
    """seasynth's frames against a volumetric path tracer of the same scene: PSNR, MAE, time, per term."""
    from seasynth.bench.fidelity import CONFIGS, WORLD_CONFIGS, parse_config, run
    from seasynth.bench.fidelity import export_scenes as export

    pinned = {**CONFIGS, **WORLD_CONFIGS}
    chosen: dict[str, str] = {}
    for c in config or list(CONFIGS):
        name, _, text = c.partition("=")
        if not text and name not in pinned:
            raise typer.BadParameter(f"unknown configuration {name!r}; pinned: {', '.join(pinned)}",
                                     param_hint="--config")
        chosen[name] = text or pinned[name]
        parse_config(chosen[name])
    size = _size(resolution)
    if export_scenes is not None:
        for path in export(export_scenes, configs=chosen, platform=gl, size=size):
            typer.echo(str(path))
        return
    if out is None:
        raise typer.BadParameter("give --out (or --export-scenes)", param_hint="--out")
    run(out, configs=chosen, spp=spp, repeats=repeats, machine=machine, platform=gl, references=references,
        timing_spp=timing_spp, size=size, forward_scatter=forward_scatter)


@bench_app.command("calibration")
def bench_calibration(
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for calibration.json and .md.")] = None,
    scene: Annotated[Optional[list[str]], typer.Option("--scene", help="Scene name (repeatable).")] = None,
    water: Annotated[Optional[list[str]], typer.Option("--water", help="Jerlov type (repeatable).")] = None,
    frames: Annotated[int, typer.Option("--frames", min=1, help="Frames per scene.")] = 3,
    width: Annotated[int, typer.Option("--width", min=16)] = 160,
    height: Annotated[int, typer.Option("--height", min=16)] = 120,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
    light: Annotated[str, typer.Option("--light", help="The clean frames' light model: paper (the table's: J does "
                                       "not change with range) or physical (J falls with depth).")] = "paper",
) -> None:
    """Water calibration against known water: seasynth's clean frames hazed with Jerlov types, estimated back."""
    from seasynth.bench.calibration import run

    run(out, scenes=scene, waters=water, frames=frames, width=width, height=height, machine=machine, platform=gl,
        light=light)


@bench_app.command("blender")
def bench_blender(
    spec: Annotated[Path, typer.Option("--spec", help="Scene spec.")] = Path("examples/urchins.yaml"),
    frames: Annotated[int, typer.Option("--frames", min=2, help="Scenes Blender renders per configuration.")] = 3,
    width: Annotated[int, typer.Option("--width", min=16)] = 640,
    height: Annotated[int, typer.Option("--height", min=16)] = 480,
    engine: Annotated[Optional[list[str]], typer.Option("--engine", help="Blender configuration (repeatable): "
                                                       "cycles-16, cycles-16-oidn, cycles-64, eevee-16.")] = None,
    blender_python: Annotated[Path, typer.Option("--blender-python", help="A Python with bpy 4.5 (bpy needs "
                                                 "numpy<2, so not seasynth's).")] = Path(".venv-blender/bin/python"),
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for blender.json, .md and .png.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """seasynth's generate against Blender (Cycles, EEVEE) on the same sampled scenes: seconds per frame, ratio."""
    from seasynth.bench.blender import ENGINES, run

    for name in engine or []:
        if name not in ENGINES:
            raise typer.BadParameter(f"unknown configuration {name!r}; known: {', '.join(ENGINES)}",
                                     param_hint="--engine")
    run(spec, frames=frames, width=width, height=height, out=out, blender_python=blender_python,
        engines=engine or list(ENGINES), platform=gl)


@bench_app.command("transfer")
def bench_transfer(
    work: Annotated[Path, typer.Option("--work", help="Folder for the test set, datasets, exports and runs "
                                       "(resumable: what is complete there is kept).")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Folder for transfer.json, .md and .png.")] = None,
    recipe: Annotated[Path, typer.Option("--recipe", help="The bench's recipe.")] = Path("bench/recipes/transfer.json"),
    device: Annotated[str, typer.Option("--device", help="torch device of the detector: cuda or cpu.")] = "cuda",
    path_tracer: Annotated[str, typer.Option("--path-tracer", help="Mitsuba variant of the test set: cuda_ad_rgb "
                                             "(an NVIDIA GPU) or llvm_ad_rgb (the CPU).")] = "cuda_ad_rgb",
    jobs: Annotated[int, typer.Option("--jobs", min=1, help="Detectors trained at once, each in its own process; "
                                      "with --device cuda, process k on GPU cuda:k (datasets render over every GPU "
                                      "EGL finds).")] = 1,
    testset_jobs: Annotated[int, typer.Option("--testset-jobs", min=0, help="With --jobs above 1: path tracers "
                                              "rendering the test set at once, each its own process (process k on "
                                              "GPU k mod the GPUs), while datasets generate and detectors train; "
                                              "0: the test set first.")] = 0,
    row: Annotated[Optional[list[str]], typer.Option("--row", help="Only this row of the recipe (repeatable).")]
    = None,
    testset_shard: Annotated[Optional[str], typer.Option(
        "--testset-shard", help="K/N: only path trace the test images whose place in the set is K mod N, then stop "
        "(one process per GPU, each with CUDA_VISIBLE_DEVICES=K); a later run without it finds them done.")] = None,
    keep: Annotated[bool, typer.Option("--keep", help="Keep each COCO export after training on it.")] = False,
    machine: Annotated[Optional[str], typer.Option("--machine", help="Machine description to record.")] = None,
    gl: PlatformOpt = "egl",
) -> None:
    """A detector trained only on seasynth, scored on a held-out path-traced test set (not real photographs): one
    row per ablation of the recipe, mAP50, mAP50-95, P and R at the best F1, mean and spread over replicates."""
    from seasynth.bench.pathtracer import MAX_SAMPLES_PER_CALL
    from seasynth.bench.transfer import run
    from seasynth.bench.transfer_recipe import load_recipe
    from seasynth.bench.transfer_testset import build

    if path_tracer not in MAX_SAMPLES_PER_CALL:
        raise typer.BadParameter(f"{path_tracer!r}: give one of {', '.join(MAX_SAMPLES_PER_CALL)}",
                                 param_hint="'--path-tracer'")
    if testset_shard is not None:
        build(load_recipe(recipe), work / "testset", path_tracer, gl, shard=_shard(testset_shard))
        return
    if out is None:
        raise typer.BadParameter("give --out (or --testset-shard)", param_hint="--out")
    run(recipe, out, work, device=device, variant=path_tracer, jobs=jobs, testset_jobs=testset_jobs, platform=gl,
        workers="auto",
        rows=row, keep=keep, machine=machine)


def _shard(text: str) -> tuple[int, int]:
    """--testset-shard's K/N: 0 <= K < N; a usage error otherwise."""
    k, _, n = text.partition("/")
    try:
        shard = int(k), int(n)
    except ValueError:
        shard = (-1, 0)
    if not 0 <= shard[0] < shard[1]:
        raise typer.BadParameter(f"{text!r}: give K/N with 0 <= K < N, e.g. 0/8", param_hint="'--testset-shard'")
    return shard
