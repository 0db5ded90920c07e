"""The transfer bench: its recipes keep the test set apart from every training set (seeds, meshes, textures), test
labels are the exact boxes of the path tracer's own instance ids, the metrics are COCO's, and a tiny run of
`seasynth bench transfer` goes end to end on the CPU."""

import importlib.util
import json
import re
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from seasynth.bench.transfer_metrics import evaluate, f1_point
from seasynth.bench.transfer_recipe import (
    HELD_OUT_FIRST_VARIANT,
    RECIPES,
    Recipe,
    held_out_specs,
    load_recipe,
    row_spec,
    training_variants,
)
from seasynth.bench.transfer_testset import contrast, tight_boxes
from seasynth.service.spec.scene import MAX_VARIANTS

RECIPE_FILES = sorted(RECIPES.glob("transfer*.json"))
TINY = RECIPES / "transfer-tiny.json"


@pytest.mark.parametrize("path", RECIPE_FILES, ids=lambda p: p.stem)
def test_every_test_seed_variant_and_texture_is_one_no_training_spec_of_the_recipe_draws(path):
    recipe = load_recipe(path)
    train_seeds = {row_spec(recipe, row, r).seed for row in recipe.rows
                   for r in range(len(recipe.training.dataset_seeds))}
    test = held_out_specs(recipe)
    assert {s.seed for _, s in test}.isdisjoint(train_seeds)
    for _, spec in test:  # the path tracer renders the physical light; textures on, as the product's default
        assert spec.water.enabled and spec.water.resolved_model == "physical" and spec.materials.procedural
        assert (spec.camera.width, spec.camera.height) == (recipe.width, recipe.height)
    for row in recipe.rows:
        shapes, textures = training_variants(row_spec(recipe, row, 0))
        assert max(shapes) < HELD_OUT_FIRST_VARIANT and max(textures) < HELD_OUT_FIRST_VARIANT
    for _, spec in test:  # the held-out variants H + v, v below the test spec's own counts
        assert min(HELD_OUT_FIRST_VARIANT + v for v in training_variants(spec)[0]) >= MAX_VARIANTS


def test_the_full_recipe_has_the_paper_s_rows_and_a_test_set_of_at_least_300_images():
    recipe = load_recipe(RECIPES / "transfer.json")
    assert recipe.test.frames >= 300
    sizes = {r.name: r.size * recipe.training.frames_1x for r in recipe.rows}
    assert sizes["full"] == 1800 and sizes["5x"] == 9000
    assert len(recipe.training.dataset_seeds) == 3
    waters = {w for g in recipe.test.groups for w in g.overrides.get("water.jerlov", [])}
    assert len(waters) >= 5 and any("lighting.lamps" in g.overrides for g in recipe.test.groups)
    overrides = {r.name: r.overrides for r in recipe.rows}
    assert overrides["paper-water"] == {"water.model": "paper"}
    assert overrides["no-textures"] == {"materials.procedural": False}
    assert overrides["draft"] == {"quality": "draft"}


@settings(max_examples=60, deadline=None)
@given(train=st.lists(st.integers(0, 2**62), min_size=1, max_size=4, unique=True), first=st.integers(1, 2**62 - 1))
def test_a_recipe_is_refused_exactly_when_a_training_seed_reaches_the_test_range(train, first):
    data = json.loads(TINY.read_text())
    data["test"]["seed_first"] = first
    data["training"] |= {"dataset_seeds": train, "detector_seeds": list(range(len(train)))}
    if max(train) < first:
        assert Recipe.model_validate(data).test.seed_first == first
    else:
        with pytest.raises(ValidationError, match="below test.seed_first"):
            Recipe.model_validate(data)


@settings(max_examples=40, deadline=None)
@given(counts=st.lists(st.integers(1, MAX_VARIANTS), min_size=1, max_size=4), textures=st.integers(1, 64))
def test_no_valid_training_spec_draws_a_held_out_variant_or_texture(counts, textures):
    recipe = load_recipe(TINY)
    assets = [{"procedural": "rock", "variants": c} for c in counts]
    spec = row_spec(recipe, recipe.rows[0].model_copy(update={"overrides": {
        "targets.assets": [{"procedural": "urchin", "variants": counts[-1]}], "distractors.assets": assets,
        "terrain.variants": counts[0], "materials.variants": textures}}), 0)
    shapes, texture_variants = training_variants(spec)
    assert max(shapes) == max(counts) - 1 < HELD_OUT_FIRST_VARIANT
    assert max(texture_variants) < min(textures, HELD_OUT_FIRST_VARIANT)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 6))
def test_each_box_is_the_tight_box_of_its_instance_s_pixels(seed, n):
    rng = np.random.default_rng(seed)
    ids = rng.integers(0, n + 1, size=(13, 17)) * (rng.random((13, 17)) < 0.3)
    wanted = set(range(1, n + 1, 2))
    boxes = tight_boxes(ids, wanted)
    for i in wanted:
        rows, cols = np.nonzero(ids == i)
        if len(rows) == 0:
            assert i not in boxes
        else:
            assert boxes[i] == (cols.min(), rows.min(), cols.max(), rows.max())
    assert set(boxes) <= wanted


def test_contrast_is_the_largest_channel_difference_between_an_object_and_its_surroundings():
    ids = np.zeros((20, 30), np.uint32)
    ids[5:9, 10:16] = 4
    image = np.full((20, 30, 3), (40, 50, 60), np.uint8)
    image[ids == 4] = (100, 70, 60)
    image[0, 0] = 255  # beyond the ring of 3 pixels round the box: not its surroundings
    assert contrast(image, ids, 4, (10, 5, 15, 8)) == 60.0
    assert contrast(np.zeros_like(image), ids, 4, (10, 5, 15, 8)) == 0.0  # in the dark: nothing stands out


def gt(boxes_per_image: list[list[list[float]]]) -> dict:
    images = [{"id": i, "file_name": f"{i}.png", "width": 64, "height": 48} for i in range(len(boxes_per_image))]
    anns = [{"id": k + 1, "image_id": i, "category_id": 1, "bbox": b, "area": b[2] * b[3], "iscrowd": 0}
            for k, (i, b) in enumerate((i, b) for i, bs in enumerate(boxes_per_image) for b in bs)]
    return {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "Urchin"}]}


def test_perfect_detections_score_one_and_none_score_zero():
    truth = gt([[[2, 3, 10, 8], [30, 20, 12, 12]], [[5, 5, 20, 10]]])
    dets = [{"image_id": a["image_id"], "category_id": 1, "bbox": a["bbox"], "score": 0.9}
            for a in truth["annotations"]]
    assert evaluate(truth, dets) == {"map50": 1.0, "map50_95": 1.0, "precision": 1.0, "recall": 1.0, "f1": 1.0,
                                     "score_threshold": 0.9}
    assert evaluate(truth, [])["map50"] == 0.0


def test_an_ignored_box_is_neither_a_miss_when_missed_nor_a_false_positive_when_found():
    truth = gt([[[2, 3, 10, 8], [30, 20, 12, 12]]])
    truth["annotations"][1]["iscrowd"] = 1
    found = {"image_id": 0, "category_id": 1, "bbox": [2, 3, 10, 8], "score": 0.9}
    on_ignored = {"image_id": 0, "category_id": 1, "bbox": [30, 20, 12, 12], "score": 0.8}
    for dets in ([found], [found, on_ignored]):
        r = evaluate(truth, dets)
        assert (r["precision"], r["recall"]) == (1.0, 1.0) and r["map50"] == pytest.approx(1.0, abs=1e-12)


def test_precision_and_recall_are_taken_where_f1_is_best():
    truth = gt([[[2, 3, 10, 8], [30, 20, 12, 12]], [[5, 5, 20, 10], [40, 30, 10, 10]]])
    a = truth["annotations"]
    dets = [{"image_id": a[0]["image_id"], "category_id": 1, "bbox": a[0]["bbox"], "score": 0.9},
            {"image_id": a[2]["image_id"], "category_id": 1, "bbox": a[2]["bbox"], "score": 0.8},
            {"image_id": 0, "category_id": 1, "bbox": [50, 2, 6, 6], "score": 0.7},  # a false positive
            {"image_id": a[1]["image_id"], "category_id": 1, "bbox": a[1]["bbox"], "score": 0.2}]
    r = evaluate(truth, dets)
    # thresholds 0.9, 0.8, 0.7, 0.2 (4 true boxes): F1 = 2/5, 2/3, 4/7, 3/4 -> 0.2 (P 3/4, R 3/4)
    assert (r["precision"], r["recall"], r["score_threshold"]) == (0.75, 0.75, 0.2)
    assert r["f1"] == pytest.approx(0.75)
    assert r["map50"] == pytest.approx(evaluate(truth, dets[:2] + dets[3:])["map50"], abs=0.2)
    ties = f1_point(np.array([0.5, 0.5]), np.array([True, False]), 1)  # a threshold keeps equal scores together
    assert (ties["precision"], ties["recall"]) == (0.5, 1.0)


@pytest.fixture(scope="module")
def mitsuba():
    if importlib.util.find_spec("mitsuba") is None:
        pytest.skip("mitsuba is not installed (pip install -e '.[bench]')")
    from seasynth.bench import pathtracer

    pathtracer.use_libllvm()
    return pathtracer


def test_held_out_scenes_draw_only_held_out_meshes_terrains_and_textures_and_label_what_seasynth_sees(mitsuba):
    from seasynth.bench.fidelity_scene import exported_scene
    from seasynth.bench.transfer_testset import held_out_scene
    from seasynth.worker.frame.function import PRESETS, RenderSession
    from seasynth.worker.render import Passes

    _, spec = held_out_specs(load_recipe(TINY))[0]
    with RenderSession() as s:
        scene = held_out_scene(s, spec, 0)
        variants = [int(re.search(r"/(\d+)/", scene.terrain.key).group(1))]
        for p in scene.objects:
            variants += [p.variant, int(p.asset.key.rsplit("/", 1)[1])]
            variants += [int(re.search(r"texture/\w+/(\d+)/", i.key).group(1)) for i in p.material.images()]
        variants += [int(re.search(r"texture/\w+/(\d+)/", i.key).group(1)) for i in scene.terrain.material.images()]
        assert min(variants) >= HELD_OUT_FIRST_VARIANT and scene.objects
        ours = s.renderer.render(s.view(spec, scene), s.draw_items(scene), scene.light, None, PRESETS["draft"],
                                 Passes(ids=True)).instance
        traced = mitsuba.render_ids(exported_scene(s, spec, scene))
    assert np.mean(ours == traced) > 0.995  # the same geometry, seen through the same camera, at pixel centres
    targets = {p.instance_id for p in scene.objects if p.role == "target"}
    for i, box in tight_boxes(traced, targets).items():
        theirs = tight_boxes(ours, {i})[i]
        assert max(abs(a - b) for a, b in zip(box, theirs)) <= 1


def test_a_tiny_transfer_bench_runs_end_to_end_on_the_cpu(tmp_path, mitsuba):
    if importlib.util.find_spec("torch") is None or importlib.util.find_spec("torchvision") is None:
        pytest.skip("torch and torchvision are not installed (pip install -c constraints.txt -e '.[transfer]'; "
                    "bash .ci/setup installs them)")
    args = ["bench", "transfer", "--recipe", TINY, "--work", tmp_path / "work", "--out", tmp_path / "out",
            "--device", "cpu", "--path-tracer", "llvm_ad_rgb", "--machine", "ci", "--jobs", "2",
            "--testset-jobs", "2"]  # the test set renders in two processes of its own while the detectors train
    done = subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True,
                          check=False, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "out" / "transfer.json").read_text())
    recipe = load_recipe(TINY)
    assert [r["name"] for r in result["rows"]] == [r.name for r in recipe.rows]
    assert result["testset"]["images"] == recipe.test.frames and result["testset"]["boxes"] > 0
    coco = json.loads((tmp_path / "work" / "testset" / "annotations" / "instances_test.json").read_text())
    assert len(coco["annotations"]) == result["testset"]["boxes"]
    shards = [(tmp_path / "work" / f"testset-{k}.log").read_text() for k in (0, 1)]
    assert sum(log.count('"file_name"') for log in shards) == recipe.test.frames  # the shards made every image
    for row in result["rows"]:
        for k in ("precision", "recall", "map50", "map50_95"):
            assert 0.0 <= row[k]["mean"] <= 1.0 and row[k]["n"] == 1
        assert row["replicates"][0]["train_images"] == recipe.training.frames_1x
    assert "NOT real photographs" in (tmp_path / "out" / "transfer.md").read_text()
    assert (tmp_path / "out" / "transfer.png").stat().st_size > 0


def test_the_learning_rate_warms_up_linearly_then_falls_along_a_cosine_to_zero():
    from seasynth.bench.transfer_train import lr_factor

    t = load_recipe(RECIPES / "transfer.json").training
    assert [lr_factor(s, t) for s in (0, t.warmup_steps - 1)] == [1 / t.warmup_steps, 1.0]
    assert lr_factor(t.warmup_steps, t) == 1.0 and lr_factor(t.steps, t) == pytest.approx(0.0, abs=1e-12)
    mid = t.warmup_steps + (t.steps - t.warmup_steps) // 2
    assert lr_factor(mid, t) == pytest.approx(0.5, abs=1e-3)


def test_a_flip_mirrors_the_image_and_its_boxes_exactly():
    torch = pytest.importorskip("torch", reason="torch is not installed (the detector's training needs it)")
    from seasynth.bench.transfer_train import augment

    t = load_recipe(TINY).training.model_copy(update={"hflip": 1.0, "jitter": 0.0})
    img = torch.rand(3, 5, 8)
    out, boxes = augment(img, np.array([[1.0, 2.0, 3.0, 4.0]], np.float32), np.random.default_rng(0), t)
    assert torch.allclose(out, img.flip(2), rtol=0.0, atol=1e-6) and boxes.tolist() == [[5.0, 2.0, 7.0, 4.0]]


def test_a_test_set_rendered_in_shards_is_byte_for_byte_the_one_rendered_at_once(tmp_path, mitsuba):
    from seasynth.bench.transfer_testset import build

    recipe = load_recipe(TINY)
    for k in (1, 0):  # shards in any order, then the run that finds every image done and writes the json
        assert build(recipe, tmp_path / "a", "llvm_ad_rgb", shard=(k, 2), log=lambda line: None) is None
    assert len(list((tmp_path / "a" / "records").iterdir())) == recipe.test.frames
    a = build(recipe, tmp_path / "a", "llvm_ad_rgb", log=pytest.fail)  # nothing left to render
    b = build(recipe, tmp_path / "b", "llvm_ad_rgb", log=lambda line: None)
    keys = ("file_name", "boxes", "scene_sha256", "png_sha256", "noise_db")
    assert [{k: r[k] for k in keys} for r in a["records"]] == [{k: r[k] for k in keys} for r in b["records"]]
    assert a["boxes"] == sum(len(r["boxes"]) for r in b["records"]) > 0


def test_a_test_set_shard_is_k_of_n():
    import typer

    from seasynth.cli.bench import _shard

    assert _shard("0/8") == (0, 8) and _shard("7/8") == (7, 8)
    for text in ("8/8", "-1/2", "1", "a/b", "1/0"):
        with pytest.raises(typer.BadParameter, match="0 <= K < N"):
            _shard(text)
