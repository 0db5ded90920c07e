"""Generate-time exports without the service: per-shard parts merge to exactly `seasynth export` of the whole
dataset whatever the shard size, and `seasynth generate` with outputs.coco/yolo writes OUT/export/{format}/."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from local_datasets import CLOSED_FORM, EXAMPLE, closed_form_example, seasynth, tree

from seasynth.service.errors import ExportError
from seasynth.service.shards import shard_at, shard_count
from seasynth.service.spec.dataset import load_spec
from seasynth.worker.export import GENERATED_EXPORTS, SPLITS, plan_export, run_export
from seasynth.worker.export.files import EXPORT_RECORD
from seasynth.worker.export.merge import PartMerger, mcap_name
from seasynth.worker.export.parts import REBUILT_AT_MERGE, kitti_names, parts_render_spec, write_part
from seasynth.worker.local.folder import RECORD
from seasynth.worker.local.generate import generate

FRAMES = 7
SPEC = {**CLOSED_FORM, "camera.width": 48, "camera.height": 36, "frames": FRAMES, "outputs.split": [0.5, 0.25, 0.25]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Frames with instance/ and meta/, as a worker keeps them for a shard's parts (parts_render_spec)."""
    out = tmp_path_factory.mktemp("ds") / "ds"
    generate(load_spec(EXAMPLE, {**SPEC, "outputs.instance": True}), out)
    return out


def manifest_of(ds: Path, shard_size: int) -> dict:
    """What a service manifest says of the dataset, cut into shards of `shard_size`."""
    record = json.loads((ds / RECORD).read_text())
    shards = [shard_at(FRAMES, shard_size, i) for i in range(shard_count(FRAMES, shard_size))]
    return {"id": "x" * 32, "code_version": record["code_version"], "renderer": record["renderer"],
            "spec": record["spec"], "shards": [{"index": s.index, "first_frame": s.first_frame,
                                                "frame_count": s.frame_count} for s in shards]}


def merged(ds: Path, fmt: str, shard_size: int, root: Path) -> Path:
    """Every shard's part of `fmt` written as a worker writes it, then merged as `seasynth fetch --format` does."""
    man = manifest_of(ds, shard_size)
    spec = load_spec(EXAMPLE, {**SPEC, "outputs.instance": True})
    parts = []
    for s in man["shards"]:
        folder = root / "parts" / f"shard-{s['index']:06d}"
        folder.mkdir(parents=True)
        frames = range(s["first_frame"], s["first_frame"] + s["frame_count"])
        members = write_part(spec, fmt, frames, ds, folder, man["code_version"])
        files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
        assert members == [f for f in files if f not in REBUILT_AT_MERGE.get(fmt, ())]
        for rel in set(files) - set(members):  # what a worker leaves out of the part's tar
            (folder / rel).unlink()
        parts.append((s, folder))
    merger = PartMerger(fmt)
    merger.prepare(root / "out")
    merger.merge(man, parts, root / "out")
    return root / "out"


@pytest.mark.parametrize("fmt", ["coco", "yolo"])
@pytest.mark.parametrize("shard_size", [1, 3, FRAMES])
def test_merged_parts_are_byte_identical_to_one_export(dataset, tmp_path, fmt, shard_size):
    """COCO and YOLO: every file but the record (and data.yaml's absolute `path`) has the whole export's bytes."""
    whole = tmp_path / "whole"
    run_export(plan_export(dataset, fmt), whole)
    got, want = tree(merged(dataset, fmt, shard_size, tmp_path)), tree(whole)
    record = json.loads(got.pop(EXPORT_RECORD))
    want.pop(EXPORT_RECORD)
    if fmt == "yolo":
        a, b = yaml.safe_load(got.pop("data.yaml")), yaml.safe_load(want.pop("data.yaml"))
        assert a.pop("path") == str(tmp_path / "out") and b.pop("path") == str(whole)
        assert a == b
    assert got.keys() == want.keys() and got == want
    assert record["frames"] == json.loads((whole / EXPORT_RECORD).read_text())["frames"]


def test_mcap_parts_are_one_bag_per_shard_and_split(dataset, tmp_path):
    out = merged(dataset, "mcap", 3, tmp_path)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([EXPORT_RECORD] + [mcap_name(s, i) for s in SPLITS for i in range(3)])


@pytest.mark.parametrize("fmt", ["coco", "yolo", "mcap"])
def test_an_export_into_a_fetched_export_leaves_exactly_a_fresh_exports_files(dataset, tmp_path, fmt):
    """`seasynth export` into a folder `seasynth fetch --format` filled replaces it: no per-shard bag stays."""
    out = merged(dataset, fmt, 3, tmp_path)
    run_export(plan_export(dataset, fmt), out)
    fresh = tmp_path / "fresh"
    run_export(plan_export(dataset, fmt), fresh)
    got, want = tree(out), tree(fresh)
    assert sorted(got) == sorted(want)
    if fmt == "mcap":
        assert sorted(got) == sorted([EXPORT_RECORD] + [f"{split}.mcap" for split in SPLITS])
    for files in (got, want):
        files.pop("data.yaml", None)  # YOLO's names its folder
    assert got == want


def test_parts_are_pure_functions_of_the_shard(dataset, tmp_path):
    spec = load_spec(EXAMPLE, {**SPEC, "outputs.instance": True})
    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        folder.mkdir()
        write_part(spec, "coco", range(2, 5), dataset, folder, "1.2.3")
    assert tree(a) == tree(b)


def test_the_kitti_tar_keeps_only_the_spec_outputs():
    """COCO renders instance/ and meta/ for its masks; the KITTI files are still only those the spec asks for."""
    spec = load_spec(EXAMPLE, {**SPEC, "outputs.coco": True, "outputs.meta": False})
    render = parts_render_spec(spec)
    assert (render.outputs.instance, render.outputs.meta) == (True, True)
    names = ["calib/000003.txt", "image_2/000003.png", "instance/000003.png", "label_2/000003.txt",
             "meta/000003.json"]
    assert kitti_names(spec, render, 3, names) == ["calib/000003.txt", "image_2/000003.png", "label_2/000003.txt"]
    yolo = load_spec(EXAMPLE, {**SPEC, "outputs.yolo": True})
    assert parts_render_spec(yolo) is yolo  # YOLO and MCAP need no masks: nothing more is rendered


def test_a_merge_refuses_a_part_of_another_dataset(dataset, tmp_path):
    out = merged(dataset, "coco", FRAMES, tmp_path)
    man = manifest_of(dataset, FRAMES)
    man["spec"] = {**man["spec"], "seed": 99}
    with pytest.raises(ExportError, match="part was made for another dataset"):
        PartMerger("coco").merge(man, [(man["shards"][0], tmp_path / "parts" / "shard-000000")], out)


@pytest.mark.parametrize("loss", ["folder", "image", "label"])
def test_a_yolo_merge_refuses_a_part_that_lost_files(dataset, tmp_path, loss):
    """A part folder removed or emptied since it was fetched: refused naming the shard, not a complete export."""
    merged(dataset, "yolo", 3, tmp_path)
    man = manifest_of(dataset, 3)
    folder = tmp_path / "parts" / "shard-000001"
    if loss == "folder":
        for p in sorted(folder.rglob("*"), reverse=True):
            p.unlink() if p.is_file() else p.rmdir()
        folder.rmdir()
    else:
        victim = next(p for p in sorted((folder / ("images" if loss == "image" else "labels")).rglob("*"))
                      if p.is_file())
        victim.unlink()
    parts = [(s, tmp_path / "parts" / f"shard-{s['index']:06d}") for s in man["shards"]]
    with pytest.raises(ExportError, match=r"shard-000001: shard 1's YOLO part holds \d+ images and \d+ label files "
                                          r"for its 3 frames"):
        PartMerger("yolo").merge(man, parts, tmp_path / "out")


@pytest.mark.parametrize("name", ["../../../escape.png", "/abs.png", "sub/x.png", "..", ""])
def test_a_coco_merge_refuses_an_image_file_name_that_is_not_plain(dataset, tmp_path, name):
    out = merged(dataset, "coco", FRAMES, tmp_path)
    man = manifest_of(dataset, FRAMES)
    folder = tmp_path / "parts" / "shard-000000"
    path = folder / "annotations" / "instances_train.json"
    data = json.loads(path.read_text())
    data["images"][0]["file_name"] = name
    path.write_text(json.dumps(data))
    with pytest.raises(ExportError, match=f"instances_train.json: image file_name {name!r} is not a plain file name"):
        PartMerger("coco").merge(man, [(man["shards"][0], folder)], out)
    assert not (tmp_path / "escape.png").exists()


def test_generate_writes_the_spec_exports(tmp_path):
    spec = closed_form_example(tmp_path)
    out = tmp_path / "ds"
    r = seasynth("generate", spec, "--out", out, "--width", "32", "--height", "24", "--frames", "3")
    assert r.returncode == 0, r.stderr
    assert not (out / GENERATED_EXPORTS).exists()  # no export format in the spec: no export folder
    data = yaml.safe_load(spec.read_text())
    data.setdefault("outputs", {}).update(coco=True, yolo=True, split=[0.5, 0.5, 0.0])
    spec.write_text(yaml.safe_dump(data))
    r = seasynth("generate", spec, "--out", out, "--width", "32", "--height", "24", "--frames", "3", "--overwrite")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (out / GENERATED_EXPORTS).iterdir()) == ["coco", "yolo"]
    for fmt in ("coco", "yolo"):
        assert f"{out / GENERATED_EXPORTS / fmt}: {fmt} export" in r.stdout
        ref = tmp_path / f"ref-{fmt}"
        assert seasynth("export", out, "--format", fmt, "--out", ref).returncode == 0  # the spec's split by default
        got, want = tree(out / GENERATED_EXPORTS / fmt), tree(ref)
        assert json.loads(got.pop(EXPORT_RECORD))["split"] == {"train": 0.5, "val": 0.5, "test": 0.0}
        want.pop(EXPORT_RECORD)
        if fmt == "yolo":
            got.pop("data.yaml"), want.pop("data.yaml")
        assert got == want
    assert not list((out / GENERATED_EXPORTS / "coco" / "images" / "test").iterdir())
