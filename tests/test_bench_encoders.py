"""seasynth.bench.encoders' harness on small synthetic frames: no GL, every installed lossless encoder round-trips exactly."""

import json

import numpy as np
import pytest

from seasynth.bench import encoders


def frames() -> dict[str, list[np.ndarray]]:
    """A smooth gradient and noise per kind: (24, 32, 3) uint8 and (24, 32) uint16 using the full 16 bits."""
    rng = np.random.default_rng(3)
    ramp = np.add.outer(np.arange(24), np.arange(32))
    rgb = [np.stack([ramp * 5, ramp * 3, 255 - ramp * 4], axis=-1).astype(np.uint8),
           rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)]
    depth = [(ramp * 1000).astype(np.uint16), rng.integers(0, 65536, (24, 32), dtype=np.uint16)]
    return {"rgb8": rgb, "depth16": depth}


@pytest.fixture(scope="module")
def rows():
    return encoders.measure(encoders.candidates(), frames(), rounds=1, thread_seconds=0)


def test_every_installed_lossless_encoder_round_trips_exactly_and_the_baseline_runs(rows):
    ok = [r for r in rows if r["status"] == "ok"]
    lossless = [r for r in ok if r["lossless"]]
    assert all(r["exact"] and r["max_abs_error"] == 0 and r["mean_abs_error"] == 0 for r in lossless)
    # Pillow and imagecodecs are worker dependencies: today's encoder and Pillow's levels always run, on both kinds.
    for kind in encoders.KINDS:
        assert len([r for r in ok if r["image"] == kind and r["encoder"] == "Pillow PNG"]) == 5, kind
        current = [r for r in ok if r["image"] == kind and r["encoder"] == "seasynth.worker.frame.function.png_bytes"]
        assert [r["speedup_vs_current"] for r in current] == [1.0], kind
    for r in ok:
        assert r["ms_per_frame"] > 0 and r["bytes_per_frame"] > 0 and r["threads2_speedup"] > 0, r
    # Each (encoder, settings, kind) appears once; lossy rows are rgb8 only and say how far they are off.
    keys = [(r["encoder"], r["settings"], r["image"]) for r in rows]
    assert len(keys) == len(set(keys))
    lossy = [r for r in rows if not r["lossless"]]
    assert lossy and all(r["image"] == "rgb8" for r in lossy)
    assert all(r["max_abs_error"] > 0 and r["exact"] is False for r in lossy if r["status"] == "ok")


def test_an_encoder_that_is_not_installed_is_listed_and_one_that_loses_data_is_refused():
    missing = encoders.Candidate("nope", "x", True, encoders.KINDS, "no_such_module_for_seasynth", bytes)
    [a, b] = encoders.measure([missing], frames(), rounds=1, thread_seconds=0)
    assert (a["status"], b["status"], a["ms_per_frame"]) == ("not installed", "not installed", None)

    def drops_low_bit(a: np.ndarray) -> bytes:
        return encoders.candidates()[0].encode(a & ~np.array(1, a.dtype))

    liar = encoders.Candidate("liar", "x", True, ("rgb8",), "PIL", drops_low_bit)
    with pytest.raises(AssertionError, match="liar"):
        encoders.measure([liar], {"rgb8": frames()["rgb8"]}, rounds=1, thread_seconds=0)


def test_results_are_written_with_every_field_and_row(rows, tmp_path):
    result = {"machine": "test", "gl_renderer": "none", "spec": "synthetic", "resolution": [32, 24], "frames": 2,
              "rounds": 1, "versions": encoders.versions(), "rows": rows}
    encoders.write_results(result, tmp_path)
    back = json.loads((tmp_path / "encoders.json").read_text())
    assert back == result
    assert all(set(encoders.ROW_FIELDS) <= set(r) for r in back["rows"])
    table = (tmp_path / "encoders.md").read_text()
    assert "machine: test" in table and "32x24" in table
    for r in rows:
        cell = f"{r['ms_per_frame']:.2f}" if r["status"] == "ok" else r["status"]
        assert f"| {r['encoder']} | {r['settings']} | {cell} |" in table, r
