"""How many render processes `--workers auto` and `seasynth worker --concurrency auto` start: cores from the affinity
and a cgroup's CPU quota, 1.5 a core on GPUs (a multiple of the GPU count), one a core on a software renderer."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from seasynth.service.gpus import GpuChoice
from seasynth.worker.local import capacity
from seasynth.worker.local.capacity import gpus_found, gpus_found_in_child, render_processes, usable_cores


@pytest.fixture
def six_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3, 6, 7})


def test_cores_are_the_affinity_capped_by_a_cgroup_quota(six_cores, tmp_path):
    assert usable_cores(tmp_path) == 6  # no cgroup files: the affinity
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert usable_cores(tmp_path) == 6
    (tmp_path / "cpu.max").write_text("250000 100000\n")  # --cpus 2.5
    assert usable_cores(tmp_path) == 3
    (tmp_path / "cpu.max").write_text("5000 100000\n")  # a twentieth of a core still runs one process
    assert usable_cores(tmp_path) == 1
    (tmp_path / "cpu.max").write_text("garbage\n")
    assert usable_cores(tmp_path) == 6

    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert usable_cores(v1) == 6
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("400000\n")
    assert usable_cores(v1) == 4


def test_processes_are_one_a_core_on_software_and_one_and_a_half_on_gpus():
    assert [render_processes(0, c) for c in (1, 2, 16)] == [1, 2, 16]
    assert [render_processes(1, c) for c in (1, 2, 16, 15)] == [2, 3, 24, 23]
    # A multiple of the GPU count: every GPU gets as many processes (process k on GPU k mod G).
    assert [render_processes(g, 16) for g in (2, 3, 5)] == [24, 24, 25]
    assert render_processes(4, 1) == 4  # at least one a GPU


def test_auto_workers_never_exceeds_the_frames(monkeypatch):
    from seasynth.worker.local.generate import auto_workers

    monkeypatch.setattr(capacity, "usable_cores", lambda: 4)
    assert [auto_workers(n) for n in (0, 1, 3, 4, 100)] == [1, 1, 3, 4, 4]
    assert [auto_workers(n, gpus=1) for n in (0, 5, 100)] == [1, 5, 6]


def test_gpus_found_counts_what_the_choice_names_without_listing_devices(monkeypatch):
    import seasynth.worker.render.devices as devices

    monkeypatch.setattr(devices, "gpu_indices", lambda: [0, 2])
    assert gpus_found("osmesa", None) == 0 and gpus_found("osmesa", GpuChoice()) == 0
    assert gpus_found("egl:1", None) == 1
    assert gpus_found("egl", GpuChoice(indices=(0, 1, 3))) == 3
    assert gpus_found("egl", GpuChoice(count=1)) == 1
    assert gpus_found("egl", None) == 2 and gpus_found("egl", GpuChoice()) == 2
    assert gpus_found("egl", GpuChoice(count=3)) == 0  # more than found: the render processes refuse it

    def no_egl():
        raise OSError("libEGL.so.1: cannot open shared object file")

    monkeypatch.setattr(devices, "gpu_indices", no_egl)
    assert gpus_found("egl", None) == 0  # the render processes say why EGL fails, not the count


def test_gpus_found_here_and_in_a_child_agree():
    """On this machine, listing in this process and in a child give the same count (0 on a CPU-only machine,
    where EGL lists Mesa's software device only)."""
    from seasynth.worker.render.devices import gpu_indices

    here = len(gpu_indices())
    assert gpus_found_in_child("egl", None) == here == gpus_found("egl", None)
    assert gpus_found_in_child("egl", GpuChoice(indices=(0, 1))) == 2
    assert gpus_found_in_child("osmesa", None) == 0


def test_worker_concurrency_auto_is_refused_when_malformed_and_named_when_chosen():
    r = subprocess.run([sys.executable, "-m", "seasynth.cli", "worker", "--concurrency", "0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "give a count >= 1 or auto" in r.stderr and "--concurrency" in r.stderr
