"""`seasynth bench transfer`: a detector trained only on seasynth, tested on images seasynth did not make.

The test domain is a volumetric path tracer (Mitsuba 3) of held-out scenes (bench/transfer_testset.py), not real
photographs. Each row of the recipe (bench/recipes/transfer.json) is the base spec with its overrides, generated and
exported exactly as a user would (`seasynth generate`, then `seasynth export --format coco`, as subprocesses), and
trained per replicate with its own dataset seed and detector seed (bench/transfer_train.py); each replicate's
detections on the test set are scored with pycocotools (bench/transfer_metrics.py). Writes transfer.json, .md and
.png (test images with ground truth and predictions) into OUT.

WORK holds what is made on the way: the test set (testset/, resumable), each replicate's spec, dataset and export
(each dataset is removed once exported, each export once trained on, unless keep), and each replicate's detections
and scores (runs/ROW-R.json: a rerun skips replicates already scored).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import platform as host
import shutil
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from seasynth.bench.transfer_recipe import Recipe, load_recipe, recipe_digest, row_spec
from seasynth.bench.transfer_report import METRICS

# The paper's numbers on the real SeaClear test set (179 images, 718 urchins), by the row of ours that matches
# its configuration: Table II (1x: haze, terrain, distractors) and Table III (5x).
PAPER = {
    "full": {"YOLOv9": (0.521, 0.389, 0.341, 0.110), "DETR": (0.419, 0.369, 0.301, 0.103)},
    "no-distractors": {"YOLOv9": (0.334, 0.274, 0.148, 0.040), "DETR": (0.713, 0.391, 0.404, 0.130)},
    "5x": {"YOLOv9": (0.557, 0.372, 0.284, 0.103), "DETR": (0.519, 0.521, 0.409, 0.168)},
}
_device: list[str] = []  # the device of a training process (set once by _pin)


def cli(*args: str) -> None:
    """Run `seasynth ARGS` as a user would (its own process); raise with its output if it fails."""
    done = subprocess.run([sys.executable, "-m", "seasynth.cli", *args], check=False, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"seasynth {' '.join(args)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}")


def make_export(recipe: Recipe, row, replicate: int, work: Path, platform: str, workers: str,
                gpus: str | None) -> Path:
    """The COCO export (every frame in train) of replicate `replicate` of `row`, generated unless present (render
    processes spread over `gpus` as `seasynth generate --gpus` takes it; None: the default device)."""
    name = f"{row.name}-{replicate}"
    coco = work / "coco" / name
    if (coco / "annotations" / "instances_train.json").exists():
        return coco
    spec_path = work / "specs" / f"{name}.json"
    spec_path.parent.mkdir(parents=True, exist_ok=True)
    spec_path.write_text(row_spec(recipe, row, replicate).model_dump_json(indent=1) + "\n")
    data = work / "data" / name
    cli("generate", str(spec_path), "--out", str(data), "--workers", workers, "--gl", platform, "--overwrite",
        *(() if gpus is None else ("--gpus", gpus)))
    if coco.exists():
        shutil.rmtree(coco)  # an unfinished export of an earlier run
    cli("export", str(data), "--format", "coco", "--out", str(coco), "--split", "1,0,0", "--gl", platform)
    shutil.rmtree(data)
    return coco


def score(recipe_json: str, coco: str, testset: str, replicate: int, run_path: str, device: str | None,
          keep: bool, ready=None) -> dict:
    """Train replicate `replicate` on `coco`, detect on the test set (once `ready`, an event, is set: the test set
    may still be rendering while the detector trains), score; writes run_path (detections and scores) and returns
    the scores. device None: the process's pinned device."""
    import torch
    import torchvision

    from seasynth.bench.transfer_metrics import evaluate
    from seasynth.bench.transfer_train import detect, train

    recipe = Recipe.model_validate_json(recipe_json)
    t = recipe.training
    device = device or _device[0]
    name = Path(run_path).stem
    model, info = train(Path(coco), t, t.detector_seeds[replicate], device,
                        log=lambda line: print(f"{name} {line}", flush=True))
    if ready is not None:
        ready.wait()
    detections = detect(model, Path(testset), "test", device)
    gt = json.loads((Path(testset) / "annotations" / "instances_test.json").read_text())
    result = {**evaluate(gt, detections), **info, "replicate": replicate,
              "dataset_seed": t.dataset_seeds[replicate], "detector_seed": t.detector_seeds[replicate],
              "device": torch.cuda.get_device_name(device) if device.startswith("cuda") else host.processor() or "cpu",
              "torch": torch.__version__, "torchvision": torchvision.__version__}
    Path(run_path).write_text(json.dumps({"scores": result, "detections": detections}) + "\n")
    if not keep:
        shutil.rmtree(coco)
    return result


def _pin(devices, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)  # the processes share the host's cores
    _device.append(devices.get())


def _gpus() -> int:
    import torch

    return max(torch.cuda.device_count(), 1)


def start_testset(recipe_path: Path, work: Path, variant: str, platform: str, procs: int,
                  device: str) -> list[subprocess.Popen]:
    """`procs` path tracers of the test set at once, each its own `seasynth bench transfer --testset-shard k/procs`
    process (with device cuda, process k on GPU k mod the GPUs torch finds); their output goes to
    WORK/testset-k.log."""
    gpus = _gpus() if device.startswith("cuda") else 0
    started = []
    for k in range(procs):
        env = dict(os.environ) | ({"CUDA_VISIBLE_DEVICES": str(k % gpus)} if gpus else {})
        log = (work / f"testset-{k}.log").open("w")
        started.append(subprocess.Popen(
            [sys.executable, "-m", "seasynth.cli", "bench", "transfer", "--work", str(work), "--recipe",
             str(recipe_path), "--path-tracer", variant, "--gl", platform, "--testset-shard", f"{k}/{procs}"],
            env=env, stdout=log, stderr=subprocess.STDOUT))
    return started


def _finish(started: list[subprocess.Popen], work: Path) -> None:
    for k, proc in enumerate(started):
        if proc.wait() != 0:
            raise RuntimeError(f"test set shard {k}/{len(started)} exited {proc.returncode}: see "
                               f"{work / f'testset-{k}.log'}")


def run(recipe_path: Path, out: Path, work: Path, *, device: str = "cuda", variant: str = "cuda_ad_rgb",
        jobs: int = 1, testset_jobs: int = 0, platform: str = "egl", workers: str = "auto",
        rows: list[str] | None = None, keep: bool = False, machine: str | None = None, log=print) -> dict:
    """The whole bench (see the module's docstring); jobs: detectors trained at once, each in its own process (with
    device cuda, process k on GPU k mod the GPUs); testset_jobs: with jobs > 1, path tracers rendering the test set
    in processes of their own while datasets generate and detectors train (0: the test set is rendered first, here);
    rows: only these rows' names (all when None)."""
    from seasynth.bench.accuracy import write_results
    from seasynth.bench.transfer_report import format_table, picture, summarise
    from seasynth.bench.transfer_testset import build

    recipe = load_recipe(recipe_path)
    chosen = [r for r in recipe.rows if rows is None or r.name in rows]
    if rows is not None and len(chosen) != len(set(rows)):
        raise ValueError(f"unknown row(s) {sorted(set(rows) - {r.name for r in recipe.rows})}; recipe rows: "
                         f"{', '.join(r.name for r in recipe.rows)}")
    testset_dir = work / "testset"
    work.mkdir(parents=True, exist_ok=True)
    background = start_testset(recipe_path, work, variant, platform, testset_jobs, device) if jobs > 1 else []
    testset = None if background else build(recipe, testset_dir, variant, platform, log=log)
    if testset is not None:
        log(_summary(testset))
    (work / "runs").mkdir(parents=True, exist_ok=True)
    replicates = range(len(recipe.training.dataset_seeds))
    todo = [(row, r) for row in chosen for r in replicates if not (work / "runs" / f"{row.name}-{r}.json").exists()]
    spread = "auto" if device.startswith("cuda") else None  # datasets render over every GPU EGL finds
    args = {"recipe_json": recipe.model_dump_json(), "testset": str(testset_dir), "keep": keep}
    if jobs > 1:  # a process per detector trained at once; on cuda, process k keeps GPU k mod the GPUs
        ctx = multiprocessing.get_context("spawn")
        manager = ctx.Manager()
        queue, ready = manager.Queue(), manager.Event()
        gpus = _gpus() if device == "cuda" else 1
        for k in range(jobs):
            queue.put(f"cuda:{k % gpus}" if device == "cuda" else device)
        threads = max((os.cpu_count() or 1) // jobs, 1)
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_pin, initargs=(queue, threads)) as pool:
            futures = []
            try:
                for row, r in todo:  # exports are made here, one after another, while earlier ones train
                    coco = make_export(recipe, row, r, work, platform, workers, spread)
                    futures.append(pool.submit(score, coco=str(coco), replicate=r, device=None, ready=ready,
                                               run_path=str(work / "runs" / f"{row.name}-{r}.json"), **args))
                if testset is None:  # the shards' images, assembled
                    _finish(background, work)
                    testset = build(recipe, testset_dir, variant, platform, log=log)
                    log(_summary(testset))
            finally:  # the detectors go on (or fail on a missing test set) rather than wait forever
                ready.set()
                for proc in background:
                    proc.kill()
            for (row, r), f in zip(todo, futures):
                log(json.dumps({"row": row.name, "replicate": r} | _short(f.result())))
    else:
        for row, r in todo:
            coco = make_export(recipe, row, r, work, platform, workers, spread)
            s = score(coco=str(coco), replicate=r, device=device,
                      run_path=str(work / "runs" / f"{row.name}-{r}.json"), **args)
            log(json.dumps({"row": row.name, "replicate": r} | _short(s)))
    runs = {(row.name, r): json.loads((work / "runs" / f"{row.name}-{r}.json").read_text())
            for row in chosen for r in replicates}
    result = summarise(recipe, recipe_digest(recipe), chosen, runs, testset, PAPER, machine or host.node())
    result["path_tracer_variant"] = variant
    first = chosen[0].name
    write_results(out, "transfer", result, format_table(result),
                  lambda path: picture(testset_dir, runs[(first, 0)]["detections"], first, path))
    return result


def _summary(testset: dict) -> str:
    return json.dumps({k: v for k, v in testset.items() if k != "records"})


def _short(scores: dict) -> dict:
    return {k: round(scores[k], 4) for k in (*METRICS, "loss_first", "loss_last")} | {"seconds": scores["seconds"]}

