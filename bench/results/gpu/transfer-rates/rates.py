"""Device-machine rates of the transfer bench's parts, each alone: detector steps/s at several concurrencies and
batch sizes, and the path tracer's seconds and noise per test image at several spp. Prints JSON lines."""
import json, os, subprocess, sys, time
from pathlib import Path
import multiprocessing as mp

W = Path("/tmp/rates")


def trainer(args):
    coco, steps, batch, device = args
    import torch
    torch.set_num_threads(2)
    from seasynth.bench.transfer_recipe import load_recipe
    from seasynth.bench.transfer_train import train
    t = load_recipe(Path("bench/recipes/transfer.json")).training.model_copy(
        update={"steps": steps, "batch": batch, "warmup_steps": 10, "min_size": 240, "max_size": 320})
    t0 = time.perf_counter()
    _, info = train(Path(coco), t, 0, device, log=lambda line: None)
    return steps / info["seconds"]


def main():
    import torch
    from seasynth.bench.transfer import make_export
    from seasynth.bench.transfer_recipe import load_recipe
    gpus = torch.cuda.device_count()
    tiny = os.environ.get("RATES_TINY") == "1"  # a check of this script on a CPU
    recipe = load_recipe(Path("bench/recipes/transfer.json"))
    recipe = recipe.model_copy(update={"width": 320, "height": 240,
                                       "training": recipe.training.model_copy(update={"frames_1x": 8 if tiny else 400})})
    t0 = time.perf_counter()
    coco = make_export(recipe, recipe.rows[0], 0, W, "egl", "auto", "auto" if gpus else None)
    print(json.dumps({"export_400_frames_s": round(time.perf_counter() - t0, 1)}), flush=True)
    ctx = mp.get_context("spawn")
    plan = [(1, 2, 2), (2, 2, 2)] if tiny else [(1, 8, 300), (2 * gpus, 8, 300), (6 * gpus, 8, 200), (2 * gpus, 16, 200)]
    for n, batch, steps in plan:
        with ctx.Pool(n) as pool:
            t0 = time.perf_counter()
            rates = pool.map(trainer, [(str(coco), steps, batch, f"cuda:{k % gpus}" if gpus else "cpu") for k in range(n)])
        print(json.dumps({"trainers": n, "gpus": gpus, "batch": batch, "steps_per_s_each": [round(r, 2) for r in rates],
                          "images_per_s_all": round(sum(rates) * batch, 1),
                          "wall_s": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
