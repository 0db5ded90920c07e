"""The committed accuracy tables: they are of the current scenes, and they meet the targets the README quotes."""

import json
from pathlib import Path

import pytest

from bench import accuracy
from service.spec import spec_digest

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"


@pytest.mark.parametrize("machine", ["cpu", "gpu"])
def test_committed_accuracy_tables_are_of_the_current_scenes_and_meet_the_targets(machine):
    result = json.loads((RESULTS / machine / "accuracy.json").read_text())
    # Re-run `seasynth bench accuracy` when a scene (or the example it builds on) changes: these must match.
    assert result["scene_spec_sha256"] == {name: spec_digest(accuracy.scene_spec(name)) for name in accuracy.SCENES}
    assert result["repeats"] >= 5 and result["resolution"] == [640, 480]
    rows = {(r["scene"], r["preset"]): r for r in result["rows"]}
    assert sorted(rows) == sorted((s, p) for s in accuracy.SCENES for p in accuracy.PRESET_NAMES)
    for (scene, preset), r in rows.items():
        assert r["formation_error"] <= 1, (scene, preset)
    for scene in accuracy.SCENES:
        default = rows[(scene, "default")]
        assert default["psnr_db"] >= 40, scene
        # On the Pareto front of (time, PSNR): no other preset is both as fast and as accurate.
        assert not [p for p in accuracy.PRESET_NAMES if p != "default"
                    and rows[(scene, p)]["ms_per_frame"] <= default["ms_per_frame"]
                    and rows[(scene, p)]["psnr_db"] >= default["psnr_db"]], scene
    table = (RESULTS / machine / "accuracy.md").read_text()
    assert all(f"| {s} | {p} | {rows[(s, p)]['ms_per_frame']} | {rows[(s, p)]['psnr_db']} |" in table for s, p in rows)
