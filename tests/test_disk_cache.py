"""The cache of built terrain variants and texture sets that outlives runs (seasynth.worker.scene.disk_cache): where
it is, when it is off, what names its folder, what is pruned, and that frames are the same bytes with it, without
it and on a second run that builds nothing."""

import os
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.local.generate import generate
from seasynth.worker.scene.disk_cache import ENV, KEEP_DAYS, KEEP_OTHERS, cache_folder, code_digest, source_digest
from seasynth.worker.scene.materials import procedural_material
from seasynth.worker.scene.texture_cache import shared_texture_set

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"


@pytest.mark.parametrize("value", ["", "off", "OFF", " none ", "0", "false"])
def test_off_keeps_it_to_the_run(monkeypatch, value):
    monkeypatch.setenv(ENV, value)
    assert cache_folder() is None


def test_the_folder_is_named_by_this_code_and_made(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, str(tmp_path / "c"))
    folder = cache_folder()
    assert folder == tmp_path / "c" / f"variants-{code_digest()}" and folder.is_dir()
    assert cache_folder() == folder and len(code_digest()) == 20


def test_without_the_variable_it_is_the_users_cache(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_folder() == tmp_path / "xdg" / "seasynth" / f"variants-{code_digest()}"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_folder() == tmp_path / "home" / ".cache" / "seasynth" / f"variants-{code_digest()}"


def test_a_folder_that_cannot_be_made_keeps_it_to_the_run(monkeypatch, tmp_path):
    (tmp_path / "file").write_text("in the way")
    monkeypatch.setenv(ENV, str(tmp_path / "file"))
    assert cache_folder() is None


@settings(max_examples=25, deadline=None)
@given(halves=st.lists(st.integers(0, int(4 * KEEP_DAYS)), max_size=6, unique=True))
def test_of_other_codes_folders_the_last_used_are_kept_and_none_unused_for_keep_days(tmp_path_factory, halves):
    ages = [h / 2 + 0.25 for h in halves]  # days unused: distinct, and 6 hours or more from KEEP_DAYS
    base = tmp_path_factory.mktemp("cache")
    now = time.time()
    for k, age_days in enumerate(ages):
        (base / f"variants-other{k}").mkdir()
        (base / f"variants-other{k}" / "terrain-x.npz").write_bytes(b"x")
        os.utime(base / f"variants-other{k}", (now - age_days * 86400, now - age_days * 86400))
    (base / "other").mkdir()  # not a cache subfolder: never touched
    os.utime(base / "other", (now - 1e8, now - 1e8))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(ENV, str(base))
        folder = cache_folder()
    by_recency = sorted(range(len(ages)), key=lambda k: ages[k])
    kept = [f"variants-other{k}" for k in by_recency[:KEEP_OTHERS] if ages[k] < KEEP_DAYS]
    assert sorted(p.name for p in base.iterdir()) == sorted(["other", folder.name, *kept])


@settings(max_examples=30, deadline=None)
@given(files=st.dictionaries(st.sampled_from(["a.py", "b.py", "sub/c.py", "d.txt"]), st.binary(max_size=8),
                             min_size=1),
       change=st.sampled_from(["bytes", "name", "version", "txt"]))
def test_the_digest_follows_every_module_and_the_version(tmp_path_factory, files, change):
    root = tmp_path_factory.mktemp("src")
    for name, data in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(data)
    before = source_digest("1.0", [root])
    assert source_digest("1.0", [root]) == before
    py = sorted(n for n in files if n.endswith(".py"))
    if change == "version":
        assert source_digest("1.1", [root]) != before
    elif change == "txt" or not py:  # what is not a module is not code
        (root / "notes.txt").write_bytes(b"anything")
        assert source_digest("1.0", [root]) == before
    elif change == "bytes":
        (root / py[0]).write_bytes(files[py[0]] + b"#")
        assert source_digest("1.0", [root]) != before
    else:
        (root / py[0]).rename(root / "renamed.py")
        assert source_digest("1.0", [root]) != before


def _frames(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.suffix in (".png", ".json", ".txt") and p.name != "run.json"}


@pytest.mark.parametrize("workers", [1, 2])
def test_a_second_run_builds_nothing_and_every_run_writes_the_same_bytes(monkeypatch, tmp_path, workers):
    # Terrain variants and texture sets; the water's solved columns are the next test's (with columns, the runs
    # without a cache folder solved them in every process: 200 s of this test's time on the 2-core CPU).
    spec = load_spec(EXAMPLE, {"camera.width": 64, "camera.height": 48, "frames": 3, "water.solved_column": False})
    monkeypatch.setenv(ENV, "off")
    generate(spec, tmp_path / "off", workers=workers)
    monkeypatch.setenv(ENV, str(tmp_path / "cache"))
    for kept in (procedural_material, shared_texture_set):  # workers=1 renders in this process, which kept them
        kept.cache_clear()
    generate(spec, tmp_path / "first", workers=workers)
    stored = {p.name: p.stat().st_mtime_ns for p in cache_folder().iterdir()}
    assert any(n.startswith("terrain-") for n in stored) and any(n.startswith("texture-") for n in stored)
    generate(spec, tmp_path / "second", workers=workers)
    assert {p.name: p.stat().st_mtime_ns for p in cache_folder().iterdir()} == stored  # read, not built again
    off = _frames(tmp_path / "off")
    assert off and _frames(tmp_path / "first") == off and _frames(tmp_path / "second") == off


def test_a_solved_water_column_read_from_the_shared_folder_is_the_solved_one_field_by_field(tmp_path):
    import dataclasses

    import numpy as np

    from seasynth.worker.light.column import Column
    from seasynth.worker.light.solved import unit_column
    from seasynth.worker.scene.disk_cache import share_in

    args = [(0.8, 0.92, 0.7), (0.55, 0.9, None)]  # a sun column and a sky column
    try:
        unit_column.cache_clear()
        solved = [unit_column(*a) for a in args]  # no folder: solved here
        share_in(tmp_path)
        unit_column.cache_clear()
        stored = [unit_column(*a) for a in args]  # solved again and stored
        assert len(list(tmp_path.glob("column-*.npz"))) == len(args)
        unit_column.cache_clear()
        read = [unit_column(*a) for a in args]  # read
    finally:
        share_in(None)
        unit_column.cache_clear()
    for s, t, r in zip(solved, stored, read):
        for f in dataclasses.fields(Column):
            a, b, c = (np.asarray(getattr(x, f.name)) for x in (s, t, r))
            assert a.dtype == c.dtype and np.array_equal(a, b) and np.array_equal(a, c), f.name


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_a_write_stopped_midway_leaves_no_part_and_only_a_disk_error_is_swallowed(monkeypatch, tmp_path, stop):
    import numpy as np

    from seasynth.worker.scene import disk_cache

    def half_written(f, **arrays):
        f.write(b"PK\x03\x04 half")
        raise stop("stopped")

    monkeypatch.setattr(disk_cache.np, "savez", half_written)
    if stop is OSError:
        disk_cache.store_npz(tmp_path / "x.npz", {"a": np.zeros(3)})
    else:
        with pytest.raises(stop):
            disk_cache.store_npz(tmp_path / "x.npz", {"a": np.zeros(3)})
    assert list(tmp_path.iterdir()) == []


def _build_slowly(log: str, tag: int) -> str:
    with open(log, "a") as f:
        f.write(f"{tag}\n")
    time.sleep(0.4)
    return f"built by {tag}"


def _load_text(path: Path) -> str | None:
    return path.read_text() if path.exists() else None


def _one_of_many(path: str, log: str, tag: int, start: float) -> str:
    from seasynth.worker.scene.disk_cache import stored_once

    time.sleep(max(start - time.time(), 0.0))  # all processes ask at once
    return stored_once(Path(path), _load_text, lambda: _build_slowly(log, tag), lambda p, v: p.write_text(v))


def test_processes_sharing_a_folder_build_a_thing_once_and_all_read_it(tmp_path):
    """Four processes ask for the same missing file at the same moment: one builds it (under the lock), the others
    wait and read what it stored; a later ask builds nothing."""
    import multiprocessing

    path, log = tmp_path / "thing.txt", tmp_path / "builds.log"
    start = time.time() + 1.0
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        got = pool.starmap(_one_of_many, [(str(path), str(log), i, start) for i in range(4)])
    builders = log.read_text().split()
    assert len(builders) == 1 and set(got) == {f"built by {builders[0]}"}
    assert _one_of_many(str(path), str(log), 9, 0.0) == got[0] and len(log.read_text().split()) == 1
