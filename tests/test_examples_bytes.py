"""Every example's files, byte for byte: tests/data/examples.sha256.json was recorded by the command a user runs
(`seasynth generate examples/NAME.yaml --out DIR`), so a change that moves code and must not change a frame is held
to it. A change meant to alter frames records new hashes (and a new version):

    python -m tests.test_examples_bytes --write

Images and some JSON records carry the last bits of the CPU's floating point: OpenBLAS and numpy pick their kernels
by the CPU, so the same code on two x86-64 machines wrote every camera image, sonar image, meta file and a third of
the navigation records of the examples with other bytes, their labels, masks, calibration and dataset records equal
(OpenBLAS's kernels alone moved meta floats by up to 2.1e-15 of their value). So the record keeps, per machine
(`platform()`: GL renderer, CPU, numpy and its SIMD level), the bytes of those files (CPU_BOUND), and for every
machine a portable summary of them: a JSON file's digest with its floats rounded to ROUND_DIGITS significant
digits, an image's mean per channel. On a recorded machine every byte is checked; on any other, every other file's
bytes and these summaries (MEAN_TOLERANCE).
"""

from __future__ import annotations

import hashlib
import json
import math
import platform as host
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
HASHES = ROOT / "tests" / "data" / "examples.sha256.json"
EXAMPLES = sorted(p.stem for p in (ROOT / "examples").glob("*.yaml"))
SEASYNTH = Path(sys.executable).with_name("seasynth")  # the console script users run, beside this interpreter
ROUND_DIGITS = 9  # the CPU's differences are at 1e-16 relative; the code's own changes far above 1e-9
MEAN_TOLERANCE = 0.02  # in the image's own steps: a thousand pixels 1 apart move a 640x480 mean by 0.003
# The files whose bytes follow the CPU (module docstring): camera and sonar images, meta and navigation records.
CPU_BOUND = ("image_2/", "meta/", "fls/", "fls_fan/", "sss/", "nav/")
SIMD_LEVELS = ("X86_V2", "X86_V3", "X86_V4", "AVX512_ICL", "AVX512_SPR")  # numpy's x86-64 levels, lowest first


def generate(name: str, out: Path) -> dict[str, bytes]:
    """Every file `seasynth generate` writes for example `name` (two render processes: the frames are the same with
    any number), keyed by path relative to `out`; the dataset record as `located` gives it."""
    run = subprocess.run([str(SEASYNTH), "generate", str(ROOT / "examples" / f"{name}.yaml"), "--out", str(out),
                          "--workers", "2"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return {str(p.relative_to(out)): located(p) for p in sorted(out.rglob("*")) if p.is_file()}


def located(path: Path) -> bytes:
    """A file's bytes; the dataset record of an example that names the checkout's own files (its assets, made
    absolute as the spec file is loaded) with those paths written as <repo> and without its spec digest, which
    digests them: the same bytes wherever the repo is checked out."""
    data = path.read_bytes()
    if path.name != "seasynth.json" or str(ROOT).encode() not in data:
        return data
    record = json.loads(data)
    record.pop("spec_sha256")
    return json.dumps(record, sort_keys=True).replace(str(ROOT), "<repo>").encode()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def rounded(value):
    """value with every float rounded to ROUND_DIGITS significant digits."""
    if isinstance(value, float) and math.isfinite(value) and value != 0.0:
        return float(f"{value:.{ROUND_DIGITS - 1}e}")
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v) for v in value]
    return value


def summary(path: str, data: bytes):
    """The portable summary of a CPU-bound file: a JSON file's rounded digest, a PNG's mean per channel (a list)."""
    if path.endswith(".json"):
        return sha(json.dumps(rounded(json.loads(data)), sort_keys=True).encode())
    import imageio.v3 as iio

    pixels = np.asarray(iio.imread(data, extension=".png"), dtype=np.float64)
    return [round(float(m), 4) for m in pixels.reshape(-1, pixels.shape[-1] if pixels.ndim == 3 else 1).mean(axis=0)]


def cpu_bound(path: str) -> bool:
    return path.startswith(CPU_BOUND)


def platform(renderer: str) -> str:
    """What a CPU-bound file's bytes depend on besides the code: the GL renderer, the CPU, numpy and its SIMD level."""
    from numpy._core._multiarray_umath import __cpu_features__ as features

    simd = ([level for level in SIMD_LEVELS if features.get(level)] or ["baseline"])[-1]
    return f"{renderer} | {cpu_name()} | numpy {np.__version__} {simd}"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return host.processor() or host.machine()


def portable(files: dict[str, bytes]) -> dict:
    """One example's record on any machine: every file's sha256 but the CPU-bound ones', which are summarised."""
    return {"sha256": {p: sha(d) for p, d in files.items() if not cpu_bound(p)},
            "summary": {p: summary(p, d) for p, d in files.items() if cpu_bound(p)}}


def differences(got: dict, want: dict) -> dict[str, tuple]:
    """The files where two portable records disagree: a file one lacks, another sha256 or JSON digest, or a mean
    further than MEAN_TOLERANCE."""
    out = {}
    for kind in ("sha256", "summary"):
        for p in sorted(set(got[kind]) | set(want[kind])):
            a, b = got[kind].get(p), want[kind].get(p)
            near = (isinstance(a, list) and isinstance(b, list) and len(a) == len(b)
                    and all(abs(x - y) <= MEAN_TOLERANCE for x, y in zip(a, b, strict=True)))
            if a != b and not near:
                out[p] = (a, b)
    return out


def renderer_of(files: dict[str, bytes]) -> str:
    return json.loads(files["seasynth.json"])["renderer"]


def test_every_example_has_recorded_hashes():
    recorded = json.loads(HASHES.read_text())
    assert sorted(recorded["examples"]) == EXAMPLES
    for machine in recorded["platforms"].values():
        assert sorted(machine) == EXAMPLES


def test_the_summaries_see_what_a_change_of_code_would_change():
    """A meta float moved in its ninth digit, or one pixel in ten moved by 8, changes the summary past what is
    allowed; a move in the fourteenth digit, or four pixels moved by 1, does not."""
    meta = json.dumps({"pose": [0.12345678901234, 2.0], "n": 3}).encode()
    last, ninth = meta.replace(b"01234,", b"01237,"), meta.replace(b"8901234,", b"9001234,")
    assert last != meta and ninth != meta
    assert summary("meta/0.json", meta) == summary("meta/0.json", last)
    assert summary("meta/0.json", meta) != summary("meta/0.json", ninth)
    import imageio.v3 as iio

    image = np.random.default_rng(0).integers(0, 240, (48, 64, 3), dtype=np.uint8)
    moved = image.copy()
    moved[::5, ::2] += 8
    near = image.copy()
    near[0, :4] += 1
    mean, near_mean, moved_mean = (summary("image_2/0.png", iio.imwrite("<bytes>", a, extension=".png"))
                                   for a in (image, near, moved))
    assert near_mean != mean and all(abs(a - b) <= MEAN_TOLERANCE for a, b in zip(mean, near_mean, strict=True))
    assert any(abs(a - b) > MEAN_TOLERANCE for a, b in zip(mean, moved_mean, strict=True))


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_files_are_byte_identical_to_the_recorded_ones(name, tmp_path):
    recorded = json.loads(HASHES.read_text())
    files = generate(name, tmp_path)
    assert differences(portable(files), recorded["examples"][name]) == {}
    exact = recorded["platforms"].get(platform(renderer_of(files)))
    if exact is not None:  # a recorded machine: the CPU-bound files' every byte too
        assert {p: sha(d) for p, d in files.items() if cpu_bound(p)} == exact[name]


if __name__ == "__main__":
    import tempfile

    if sys.argv[1:] != ["--write"]:
        sys.exit(f"usage: python -m tests.test_examples_bytes --write  (records {HASHES.relative_to(ROOT)})")
    with tempfile.TemporaryDirectory() as tmp:
        made = {name: generate(name, Path(tmp) / name) for name in EXAMPLES}
    here = platform(renderer_of(made[EXAMPLES[0]]))
    examples = {name: portable(files) for name, files in made.items()}
    old = json.loads(HASHES.read_text()) if HASHES.exists() else {}
    # Other machines' bytes are kept while this one's portable record agrees with the one they were recorded with.
    same = "platforms" in old and set(old["examples"]) == set(examples) and not any(
        differences(examples[n], old["examples"][n]) for n in examples)
    platforms = {**(old.get("platforms", {}) if same else {}),
                 here: {name: {p: sha(d) for p, d in files.items() if cpu_bound(p)} for name, files in made.items()}}
    HASHES.write_text(json.dumps({"examples": old["examples"] if same else examples, "platforms": platforms},
                                 indent=1, sort_keys=True) + "\n")
    print(f"{sum(map(len, made.values()))} files of {len(made)} examples recorded in {HASHES} for {here}"
          f"{'' if same else ' (the portable record anew: other machines dropped)'}")
