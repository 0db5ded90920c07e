"""Render processes bound to GPUs: the --gpus / SEASYNTH_GPU(S) choice, the process -> device mapping, the EGL
device check, and frames that stay byte-identical whichever device renders them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from seasynth.service.errors import RenderError
from seasynth.service.gpus import GpuChoice, gpu_for_worker, parse_gpus

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


def test_process_k_takes_the_kth_device_round_robin():
    assert [gpu_for_worker(k, (0, 1)) for k in range(5)] == [0, 1, 0, 1, 0]
    assert [gpu_for_worker(k, (3, 1, 2)) for k in range(4)] == [3, 1, 2, 3]
    assert [gpu_for_worker(k, ()) for k in range(3)] == [None, None, None]  # nothing bound: the default device
    with pytest.raises(ValueError, match="worker index"):
        gpu_for_worker(-1, (0,))


@pytest.mark.parametrize(("text", "choice"), [
    ("auto", GpuChoice()), (" AUTO ", GpuChoice()), ("2", GpuChoice(count=2)),
    ("0,1", GpuChoice(indices=(0, 1))), ("1,", GpuChoice(indices=(1,))), ("3, 2", GpuChoice(indices=(3, 2))),
])
def test_gpus_parse(text, choice):
    assert parse_gpus(text) == choice
    assert parse_gpus(str(choice)) == choice  # what a spawned process or a log line carries reads back the same


@pytest.mark.parametrize("text", ["", "x", "0", "-1", "0,-1", ",", "auto,1"])
def test_gpus_refused_with_the_forms_it_takes(text):
    with pytest.raises(ValueError, match="give auto, a count N, or comma-separated device indices"):
        parse_gpus(text)


def test_choice_resolves_against_the_gpus_found():
    found = [0, 2]  # EGL device 1 is no GPU (Mesa's software device, say)
    assert GpuChoice().resolve(found) == (0, 2) and GpuChoice().resolve([]) == ()
    assert GpuChoice(count=1).resolve(found) == (0,)
    assert GpuChoice(indices=(1,)).resolve(found) == (1,)  # an index names any EGL device
    with pytest.raises(RenderError, match="3 GPUs asked for, but EGL finds 2 GPU device"):
        GpuChoice(count=3).resolve(found)


def test_settings_take_one_gpu_or_a_spread(monkeypatch):
    from seasynth.service.settings import Settings

    monkeypatch.setenv("SEASYNTH_GPU", "1")
    assert Settings().gpu_choice == GpuChoice(indices=(1,))
    monkeypatch.delenv("SEASYNTH_GPU")
    monkeypatch.setenv("SEASYNTH_GPUS", "auto")
    assert Settings().gpu_choice == GpuChoice()
    monkeypatch.setenv("SEASYNTH_GPUS", "")
    assert Settings().gpu_choice is None
    monkeypatch.setenv("SEASYNTH_GPU", "1")  # a blank SEASYNTH_GPUS (over the GPU image's auto) is unset
    assert Settings().gpu_choice == GpuChoice(indices=(1,))
    monkeypatch.setenv("SEASYNTH_GPUS", "1,")  # what the GPU image's docs give for one device
    monkeypatch.delenv("SEASYNTH_GPU")
    assert Settings().gpu_choice == GpuChoice(indices=(1,))
    monkeypatch.delenv("SEASYNTH_GPUS")
    for env in ({"SEASYNTH_GPUS": "many"}, {"SEASYNTH_GPUS": "auto", "SEASYNTH_GPU": "0"}, {"SEASYNTH_GPU": "-1"}):
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        with pytest.raises(ValueError, match="(?i)gpu"):
            Settings()
        monkeypatch.delenv("SEASYNTH_GPU", raising=False)
        monkeypatch.delenv("SEASYNTH_GPUS", raising=False)


def test_platform_names_bind_a_device_only_on_egl():
    from seasynth.service.gpus import parse_platform
    from seasynth.worker.render.devices import gl_platform

    assert parse_platform("egl") == ("egl", None) and parse_platform("egl:2") == ("egl", 2)
    assert parse_platform("egl", 1) == ("egl", 1) and gl_platform("egl", 1) == "egl:1"
    assert gl_platform("osmesa", None) == "osmesa"
    for platform, gpu in (("osmesa", 0), ("osmesa:0", None), ("egl:x", None), ("egl:1", 2), ("vulkan", None)):
        with pytest.raises(RenderError, match="platform"):
            parse_platform(platform, gpu)


def test_an_egl_device_out_of_range_names_it_and_the_count():
    from seasynth.worker.render.devices import egl_devices
    from seasynth.worker.render.gl import GLRenderer

    count = len(egl_devices())
    with pytest.raises(RenderError, match=rf"GPU device {count + 3} asked for, but EGL finds {count} device"):
        GLRenderer(gpu=count + 3)
    with GLRenderer(gpu=count - 1) as r:  # the last device there is renders
        assert r.gpu == count - 1 and r.name


def test_auto_on_a_machine_without_gpus_binds_nothing(monkeypatch):
    from seasynth.worker.render import devices

    monkeypatch.setattr(devices, "gpu_indices", lambda: [])
    assert [devices.platform_for_worker("egl", GpuChoice(), k) for k in range(2)] == ["egl", "egl"]
    assert devices.platform_for_worker("osmesa", GpuChoice(), 0) == "osmesa"
    monkeypatch.setattr(devices, "gpu_indices", lambda: [0, 1])
    assert [devices.platform_for_worker("egl", GpuChoice(), k) for k in range(3)] == ["egl:0", "egl:1", "egl:0"]
    assert devices.platform_for_worker("egl", None, 5) == "egl"
    with pytest.raises(RenderError, match="osmesa platform renders on the CPU"):
        devices.platform_for_worker("osmesa", GpuChoice(indices=(0,)), 0)


def seasynth(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "seasynth.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_generate_on_gpus_writes_the_same_bytes_as_without(tmp_path):
    """--gpus auto (on this machine: no GPU, so the default device) and an explicit device (0, the one EGL device
    every machine that renders has) give the files a run without --gpus gives."""
    data = yaml.safe_load(EXAMPLE.read_text())
    data.update(frames=4, camera={**data["camera"], "width": 32, "height": 24}, quality="draft")
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(data))
    runs = {"plain": (), "auto": ("--gpus", "auto"), "device0": ("--gpus", "0,")}
    for name, extra in runs.items():
        r = seasynth("generate", spec, "--out", tmp_path / name, "--workers", "2", *extra)
        assert r.returncode == 0, r.stderr
    plain = tmp_path / "plain"
    files = sorted(p.relative_to(plain) for p in plain.rglob("*") if p.is_file())
    assert len(files) >= 4 * 4
    for name in runs:
        assert sorted(p.relative_to(tmp_path / name) for p in (tmp_path / name).rglob("*") if p.is_file()) == files
        assert all((tmp_path / name / f).read_bytes() == (plain / f).read_bytes() for f in files), name


def test_generate_refuses_bad_gpus_with_one_line(tmp_path):
    r = seasynth("generate", EXAMPLE, "--out", tmp_path / "a", "--gpus", "many")
    assert r.returncode == 2 and "Invalid value for '--gpus'" in r.stderr
    r = seasynth("generate", EXAMPLE, "--out", tmp_path / "b", "--frames", "2", "--width", "32", "--height", "24",
                 "--gpus", "7,", "--workers", "2")
    assert r.returncode == 1 and "GPU device 7 asked for, but EGL finds" in r.stderr and "Traceback" not in r.stderr
    # Refused before OUT is made, so the corrected command runs as it is.
    assert not (tmp_path / "b").exists()
    for extra in (("--gpus", "7,", "--workers", "1"), ("--gl", "egl:7"), ("--gpus", "9")):
        r = seasynth("generate", EXAMPLE, "--out", tmp_path / "c", "--frames", "2", *extra)
        assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
        assert ("9 GPUs asked for, but EGL finds" if extra[1] == "9" else "GPU device 7 asked for, but EGL finds") \
            in r.stderr
        assert not (tmp_path / "c").exists()
    r = seasynth("generate", EXAMPLE, "--out", tmp_path / "c", "--gl", "egl:0", "--gpus", "0,")
    assert r.returncode == 1 and "GL platform 'egl:0' binds one device and --gpus 0, spreads over GPUs" in r.stderr
    assert not (tmp_path / "c").exists()
    r = seasynth("generate", EXAMPLE, "--out", tmp_path / "d", "--gl", "opengl")
    assert r.returncode == 2 and "Invalid value for '--gl': unsupported GL platform 'opengl'" in r.stderr, r.stderr
    assert not (tmp_path / "d").exists()
