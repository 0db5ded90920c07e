"""`seasynth export` on incomplete datasets, datasets without masks and fetched ones, and the command's own
refusals and report."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import pytest
from export_fixtures import FRACTIONS, SPLIT, coco, datasets, yolo  # noqa: F401 (fixtures)
from local_datasets import seasynth, tree
from PIL import Image

from seasynth.service.errors import ExportError
from seasynth.worker.export import SPLITS, plan_export, run_export
from seasynth.worker.export.files import EXPORT_RECORD
from seasynth.worker.local.folder import RECORD

# ------------------------------------------------------------------ incomplete datasets, missing masks


def incomplete_copy(ds: Path, dest: Path) -> Path:
    shutil.copytree(ds, dest)
    (dest / "image_2/000003.png").unlink()
    (dest / "label_2/000006.txt").unlink()
    record = json.loads((dest / RECORD).read_text())
    record["state"] = "incomplete"
    (dest / RECORD).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    return dest


def test_incomplete_dataset_is_refused_naming_what_is_missing(datasets, tmp_path):
    ds = incomplete_copy(datasets["masks"], tmp_path / "ds")
    with pytest.raises(ExportError) as err:
        plan_export(ds, "coco", FRACTIONS)
    message = str(err.value)
    for part in ("state 'incomplete'", "2 of 8 frames", "image_2/000003.png", "label_2/000006.txt", "--partial"):
        assert part in message
    # A record saying "incomplete" is enough, even with every file there.
    shutil.copy(datasets["masks"] / "image_2/000003.png", ds / "image_2/000003.png")
    shutil.copy(datasets["masks"] / "label_2/000006.txt", ds / "label_2/000006.txt")
    with pytest.raises(ExportError, match="incomplete"):
        plan_export(ds, "coco", FRACTIONS)


def test_partial_exports_the_complete_frames_only(datasets, coco, tmp_path):
    ds = incomplete_copy(datasets["masks"], tmp_path / "ds")
    plan = plan_export(ds, "coco", FRACTIONS, partial=True)
    assert plan.skipped == 2 and plan.frames == 6
    report = run_export(plan, tmp_path / "out")
    assert report.skipped == 2 and sum(report.frames.values()) == 6
    for split in SPLITS:
        whole = json.loads((coco / f"annotations/instances_{split}.json").read_text())
        part = json.loads((tmp_path / f"out/annotations/instances_{split}.json").read_text())
        assert part["images"] == [im for im in whole["images"] if im["id"] not in (3, 6)]
        assert part["annotations"] == [a for a in whole["annotations"] if a["image_id"] not in (3, 6)]


def test_dataset_without_instance_outputs_is_rerendered_to_the_same_masks(datasets, coco, tmp_path):
    plain = datasets["plain"]
    assert not (plain / "instance").exists()
    plan = plan_export(plain, "coco", FRACTIONS, distractors=True)
    assert plan.renders_masks
    run_export(plan, tmp_path / "plain")
    run_export(plan_export(datasets["masks"], "coco", FRACTIONS, distractors=True), tmp_path / "masks")
    for split in SPLITS:
        a = json.loads((tmp_path / f"plain/annotations/instances_{split}.json").read_text())
        b = json.loads((tmp_path / f"masks/annotations/instances_{split}.json").read_text())
        assert a["annotations"] == b["annotations"] and a["images"] == b["images"]
        assert a["categories"] == b["categories"]
    assert json.loads((tmp_path / "plain" / EXPORT_RECORD).read_text())["masks"] == "re-rendered"
    # YOLO without distractors reads label_2 only: nothing is rendered.
    assert not plan_export(plain, "yolo", FRACTIONS).renders_masks


def test_rerendering_refuses_a_frame_whose_image_differs(datasets, tmp_path):
    ds = Path(shutil.copytree(datasets["plain"], tmp_path / "ds"))
    path = ds / "image_2/000002.png"
    pixels = Image.open(path)
    buf = io.BytesIO()
    pixels.save(buf, format="PNG", compress_level=9)  # the same pixels, other bytes
    path.write_bytes(buf.getvalue())
    with pytest.raises(ExportError, match=r"image_2/000002\.png: the frame re-rendered .* differs"):
        run_export(plan_export(ds, "coco", FRACTIONS), tmp_path / "out")


def test_a_fetched_dataset_exports_like_the_generated_one(datasets, coco, tmp_path):
    ds = Path(shutil.copytree(datasets["masks"], tmp_path / "ds"))
    record = json.loads((ds / RECORD).read_text())
    (ds / RECORD).unlink()
    manifest = {"format": "seasynth-manifest/1", "id": "x", "state": "succeeded", "complete": True,
                "frames_total": record["frames"], "seed": record["seed"], "code_version": record["code_version"],
                "renderer": record["renderer"], "spec": record["spec"], "shards": []}
    (ds / "manifest.json").write_text(json.dumps(manifest))
    run_export(plan_export(ds, "coco", FRACTIONS), tmp_path / "out")
    a, b = tree(tmp_path / "out"), tree(coco)
    assert json.loads(a.pop(EXPORT_RECORD))["dataset"]["record"] == "manifest.json"
    assert json.loads(b.pop(EXPORT_RECORD))["dataset"]["record"] == RECORD
    assert a == b
    manifest.update(complete=False, state="running")
    (ds / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ExportError, match="manifest.json says it is incomplete"):
        plan_export(ds, "coco", FRACTIONS)


# ------------------------------------------------------------------ the command


def test_cli_exports_and_reports(datasets, yolo, tmp_path):
    r = seasynth("export", datasets["masks"], "--format", "yolo", "--out", tmp_path / "out", "--split", SPLIT)
    assert r.returncode == 0, r.stderr
    counts = {s: len(list((yolo / "images" / s).iterdir())) for s in SPLITS}
    assert r.stdout.splitlines()[-1] == (f"{tmp_path / 'out'}: yolo export of 8 frames (train {counts['train']}, "
                                         f"val {counts['val']}, test {counts['test']}), 0 incomplete frame(s) skipped")
    a, b = tree(tmp_path / "out"), tree(yolo)
    a.pop("data.yaml"), b.pop("data.yaml")
    assert a == b


@pytest.mark.parametrize(("args", "code", "message"), [
    (("--split", "0.5,0.6,0.1"), 2, "Invalid value for '--split'"),
    (("--split", "0.5,0.5"), 2, "Invalid value for '--split'"),
    (("--format", "voc"), 2, "Invalid value for '--format'"),
], ids=["split-sum", "split-count", "format"])
def test_cli_refuses_bad_options_with_usage_errors(datasets, tmp_path, args, code, message):
    base = {"--format": "coco", "--split": SPLIT}
    base.update(dict(zip(args[::2], args[1::2])))
    flat = [x for kv in base.items() for x in kv]
    r = seasynth("export", datasets["masks"], "--out", tmp_path / "out", *flat)
    assert r.returncode == code and message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_cli_names_a_missing_folder_and_an_incomplete_dataset(datasets, tmp_path):
    r = seasynth("export", tmp_path / "nope", "--format", "coco", "--out", tmp_path / "out")
    assert r.returncode == 1 and r.stderr == f"error: {tmp_path / 'nope'}: no such dataset folder\n"
    ds = incomplete_copy(datasets["masks"], tmp_path / "ds")
    r = seasynth("export", ds, "--format", "coco", "--out", tmp_path / "out")
    assert r.returncode == 1 and "image_2/000003.png" in r.stderr and "--partial" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "out").exists()
    r = seasynth("export", ds, "--format", "coco", "--out", tmp_path / "out", "--partial")
    assert r.returncode == 0, r.stderr
    assert "2 incomplete frame(s) skipped" in r.stdout


def test_cli_refuses_a_folder_that_is_not_an_export(datasets, tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out/notes.txt").write_text("mine")
    r = seasynth("export", datasets["masks"], "--format", "coco", "--out", tmp_path / "out")
    assert r.returncode == 1 and "holds no seasynth export" in r.stderr
    assert tree(tmp_path / "out") == {"notes.txt": b"mine"}


def test_cli_refuses_another_formats_folder_before_any_work(datasets, tmp_path):
    out = tmp_path / "out"
    run_export(plan_export(datasets["plain"], "yolo", FRACTIONS), out)
    before = tree(out)
    r = seasynth("export", datasets["plain"], "--format", "coco", "--out", out)
    assert r.returncode == 1
    assert (r.stdout, r.stderr) == ("", f"error: {out}: holds a 'yolo' export, not 'coco'; choose another folder\n")
    assert tree(out) == before
