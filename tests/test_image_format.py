"""outputs.image_format jpeg: image_2 as JPEG at jpeg_quality and every other file as a PNG dataset's; reproduced
byte for byte, exported (COCO, YOLO, MCAP) and previewed as PNG datasets are. The service side is in
tests/service/test_service_e2e.py (a frame served alone, and the fetched dataset against a local generate)."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from local_datasets import EXAMPLE, seasynth, tree
from PIL import Image
from spec_helpers import refusal

from seasynth.service.spec.dataset import DatasetSpec, load_spec, parse_spec, spec_digest
from seasynth.worker.export import export_generated
from seasynth.worker.frame.function import frame_paths
from seasynth.worker.local.generate import generate

BASE = {"frames": 4, "camera.width": 64, "camera.height": 48, "quality": "default", "outputs.instance": True,
        "terrain.variants": 1}
JPEG = {"outputs.image_format": "jpeg", "outputs.jpeg_quality": 90}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("image-format")
    made = {}
    for name, extra, workers in (("png", {}, 1), ("jpeg", JPEG, 2)):
        made[name] = root / name
        generate(load_spec(EXAMPLE, {**BASE, **extra, "outputs.coco": True, "outputs.yolo": True,
                                     "outputs.mcap": True}), made[name], workers=workers)
        export_generated(made[name])  # as `seasynth generate` does after the frames
    return made


def _pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB")).astype(np.int64)


def test_only_the_image_changes_and_it_is_a_jpeg_near_the_png(datasets):
    png, jpeg = tree(datasets["png"]), tree(datasets["jpeg"])
    sizes = []
    for i in range(4):
        n = f"{i:06d}"
        a, b = png.pop(f"image_2/{n}.png"), jpeg.pop(f"image_2/{n}.jpg")
        assert b[:3] == b"\xff\xd8\xff" and b"JFIF" in b[:16]
        diff = np.abs(_pixels(a) - _pixels(b))
        assert 0 < diff.mean() < 4 and diff.max() < 96, (diff.mean(), diff.max())
        sizes.append((len(a), len(b)))
    # Smaller together; not each: at 64x48 a dark, nearly flat frame (frame 1, deep green water) makes a 598-byte
    # PNG, below the JPEG's own headers and tables (775 bytes).
    assert sum(b for _, b in sizes) < sum(a for a, _ in sizes), sizes
    for ds in (png, jpeg):  # what differs besides: the dataset's record (its spec) and the exports (their images)
        for rel in [r for r in ds if r == "seasynth.json" or r.startswith("export/")]:
            ds.pop(rel)
    assert png == jpeg, "labels, calib, meta and instance masks do not depend on the image's format"


def test_frame_paths_name_the_jpeg():
    spec = load_spec(EXAMPLE, {**BASE, **JPEG})
    assert frame_paths(spec, 3)[0] == "image_2/000003.jpg"
    assert frame_paths(load_spec(EXAMPLE, BASE), 3)[0] == "image_2/000003.png"


def test_reproduce_gives_the_same_jpeg_bytes(datasets, tmp_path):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(json.loads((datasets["jpeg"] / "seasynth.json").read_text())["spec"]))
    r = seasynth("reproduce", spec_file, "--frame", 2, "--out", tmp_path / "again")
    assert r.returncode == 0, r.stderr
    again = (tmp_path / "again/image_2/000002.jpg").read_bytes()
    assert again == (datasets["jpeg"] / "image_2/000002.jpg").read_bytes()


def test_exports_carry_the_jpeg_files(datasets):
    root = datasets["jpeg"] / "export"
    coco = [json.loads(p.read_text()) for p in sorted((root / "coco/annotations").glob("instances_*.json"))]
    names = sorted(im["file_name"] for c in coco for im in c["images"])
    assert names == [f"{i:06d}.jpg" for i in range(4)]
    for exported in [*(root / "coco/images").rglob("*.*"), *(root / "yolo/images").rglob("*.*")]:
        assert exported.suffix == ".jpg"
        assert exported.read_bytes() == (datasets["jpeg"] / "image_2" / exported.name).read_bytes()
    assert len(list((root / "yolo/images").rglob("*.jpg"))) == 4

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    formats, frames = set(), 0
    for bag in sorted((root / "mcap").glob("*.mcap")):
        with open(bag, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _, _, _, msg in reader.iter_decoded_messages(topics=["/camera/image/compressed"]):
                formats.add(msg.format)
                frames += 1
                assert bytes(msg.data) in {(datasets["jpeg"] / f"image_2/{i:06d}.jpg").read_bytes() for i in range(4)}
    assert formats == {"jpeg"} and frames == 4


def test_preview_sheet_reads_jpeg_images(datasets, tmp_path):
    """The sheet of the JPEG dataset is pixel for pixel the sheet of the same dataset with each JPEG's decoded pixels
    stored as PNG: it shows exactly what the JPEG files hold."""
    as_png = tmp_path / "as-png"
    shutil.copytree(datasets["jpeg"], as_png, ignore=shutil.ignore_patterns("export"))
    for jpg in sorted((as_png / "image_2").glob("*.jpg")):
        Image.open(jpg).convert("RGB").save(jpg.with_suffix(".png"))
        jpg.unlink()
    record = json.loads((as_png / "seasynth.json").read_text())
    record["spec"]["outputs"].update(image_format="png", jpeg_quality=95)
    (as_png / "seasynth.json").write_text(json.dumps(record))
    sheets = {}
    for name, root in (("jpeg", datasets["jpeg"]), ("as-png", as_png)):
        r = seasynth("preview", root, "--out", tmp_path / f"{name}.png")
        assert r.returncode == 0, r.stderr
        sheets[name] = np.asarray(Image.open(tmp_path / f"{name}.png"))
    assert sheets["jpeg"].shape == sheets["as-png"].shape and np.array_equal(sheets["jpeg"], sheets["as-png"])


@pytest.mark.parametrize(("outputs", "field"), [
    ({"jpeg_quality": 80}, "outputs.jpeg_quality"),  # a quality with the lossless format: same files, other digest
    ({"image_format": "jpeg", "jpeg_quality": 0}, "outputs.jpeg_quality"),
    ({"image_format": "jpeg", "jpeg_quality": 101}, "outputs.jpeg_quality"),
    ({"image_format": "webp"}, "outputs.image_format"),
])
def test_bad_image_format_settings_are_refused_naming_the_field(outputs, field):
    got = refusal({"outputs": outputs})
    assert any(line.startswith(field) for line in got), got


def test_a_stored_png_spec_with_every_field_validates_again():
    spec = load_spec(EXAMPLE, BASE)
    again = parse_spec(json.loads(spec.model_dump_json()))
    assert again == spec and spec_digest(again) == spec_digest(spec)
    assert parse_spec({"outputs": {"image_format": "png", "jpeg_quality": 95}}) == DatasetSpec()


def test_jpeg_bytes_do_not_depend_on_the_cpus_simd(datasets):
    """libjpeg-turbo picks SIMD code by CPU (AVX2, SSE2, or plain C): every path must give the same bytes, or
    workers on different hosts would write different files. Its JSIMD_FORCE* switches choose the path here (on a
    CPU without AVX2 the default is one of the others)."""
    code = ("import sys, imagecodecs, numpy as np\n"
            "from seasynth.worker.frame.encode import encode_image\n"
            "from seasynth.service.spec.dataset import load_spec\n"
            "from PIL import Image\n"
            "spec = load_spec(sys.argv[1], {'outputs.image_format': 'jpeg', 'outputs.jpeg_quality': 90})\n"
            "image = np.asarray(Image.open(sys.argv[2]).convert('RGB'))\n"
            "sys.stdout.buffer.write(encode_image(image, spec.outputs))\n")
    source = datasets["png"] / "image_2/000001.png"  # a rendered frame's pixels
    runs = {force: subprocess.run([sys.executable, "-c", code, str(EXAMPLE), str(source)], capture_output=True,
                                  env={**os.environ, **({force: "1"} if force else {})}, timeout=60)
            for force in ("", "JSIMD_FORCENONE", "JSIMD_FORCESSE2")}
    assert all(r.returncode == 0 and r.stdout[:3] == b"\xff\xd8\xff" for r in runs.values()), runs
    assert len({r.stdout for r in runs.values()}) == 1
