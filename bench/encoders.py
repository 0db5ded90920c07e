"""Image encoders for our frames, side by side: ms, bytes, exact round trip and 2-thread speedup per encoder.

    PYOPENGL_PLATFORM=egl PYGLET_HEADLESS=1 python -m seasynth.bench.encoders --out DIR [--width 1920 --height 1080] [--frames N]

renders N frames of examples/urchins.yaml through RenderSession (image_2 as rgb8, KITTI depth as depth16), encodes
each with every candidate that is installed, and writes DIR/encoders.md and DIR/encoders.json. The harness
(`candidates`, `measure`, `write_results`) needs no GL: tests call it on small synthetic arrays.
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import math
import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "urchins.yaml"
THREAD_SECONDS = 0.3  # one-thread work per 2-thread comparison: long enough to outlast scheduling noise
KINDS = ("rgb8", "depth16")  # (h, w, 3) uint8 sRGB image_2; (h, w) uint16 KITTI depth, metres * 256
PACKAGES = ("numpy", "Pillow", "opencv-python-headless", "imagecodecs", "pyspng", "fpng", "simplejpeg")
ROW_FIELDS = ("image", "encoder", "settings", "lossless", "status", "ms_per_frame", "bytes_per_frame",
              "compression_ratio", "speedup_vs_current", "exact", "threads2_speedup", "max_abs_error",
              "mean_abs_error")


@dataclass(frozen=True)
class Candidate:
    encoder: str  # library and format, e.g. "Pillow PNG"
    settings: str
    lossless: bool
    kinds: tuple[str, ...]  # the KINDS it can encode
    needs: str  # "module" or "module:attribute" that must import for it to run
    encode: Callable[[np.ndarray], bytes]  # takes a C-contiguous array of one of `kinds`
    current: bool = False  # what seasynth.worker.frame.function encodes with today: the baseline of speedup_vs_current


def _pillow(fmt: str, **opts) -> Callable[[np.ndarray], bytes]:
    def encode(a: np.ndarray) -> bytes:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format=fmt, **opts)
        return buf.getvalue()

    return encode


def _cv2_png(**params: int | str) -> Callable[[np.ndarray], bytes]:
    """cv2.imencode('.png'); params name cv2 constants (IMWRITE_PNG_STRATEGY="IMWRITE_PNG_STRATEGY_RLE")."""

    def encode(a: np.ndarray) -> bytes:
        import cv2

        flat = []
        for name, value in params.items():
            flat += [getattr(cv2, name), getattr(cv2, value) if isinstance(value, str) else value]
        if a.ndim == 3:  # OpenCV writes BGR: the swap is part of its cost
            a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".png", a, flat)
        if not ok:
            raise RuntimeError(f"cv2.imencode('.png', {params}) failed on {a.shape} {a.dtype}")
        return buf.tobytes()

    return encode


def _call(module: str, func: str, **kw) -> Callable[[np.ndarray], bytes]:
    def encode(a: np.ndarray) -> bytes:
        return getattr(importlib.import_module(module), func)(a, **kw)

    return encode


def _png_bytes(a: np.ndarray) -> bytes:
    from seasynth.worker.frame.encode import png_bytes

    return png_bytes(a)


def _sub_png(codec: str, level: int) -> Callable[[np.ndarray], bytes]:
    """A PNG whose rows are SUB-filtered here and whose zlib stream comes from imagecodecs' `codec`_encode
    (zlibng: zlib-ng; deflate: libdeflate), to weigh faster deflaters against libpng's zlib."""

    def encode(a: np.ndarray) -> bytes:
        import struct
        import zlib

        import imagecodecs

        grey16 = a.ndim == 2
        rows = (a.astype(">u2") if grey16 else a).view(np.uint8).reshape(a.shape[0], -1)
        bpp = 2 if grey16 else 3
        filtered = np.empty((rows.shape[0], rows.shape[1] + 1), np.uint8)
        filtered[:, 0] = 1  # SUB
        filtered[:, 1:1 + bpp] = rows[:, :bpp]
        np.subtract(rows[:, bpp:], rows[:, :-bpp], out=filtered[:, 1 + bpp:])

        def chunk(kind: bytes, data: bytes) -> bytes:
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

        head = struct.pack(">IIBBBBB", a.shape[1], a.shape[0], 16 if grey16 else 8, 0 if grey16 else 2, 0, 0, 0)
        body = bytes(getattr(imagecodecs, f"{codec}_encode")(filtered.tobytes(), level=level))
        return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + chunk(b"IDAT", body) + chunk(b"IEND", b"")

    return encode


def candidates() -> list[Candidate]:
    """Every encoder we compare, installed or not (built on call: nothing is imported here)."""
    from seasynth.worker.frame.encode import PNG_SETTINGS

    both, rgb = KINDS, ("rgb8",)
    settings = ", ".join(f"{k}={v}" for k, v in PNG_SETTINGS.items())
    c = [Candidate("seasynth.worker.frame.function.png_bytes", f"imagecodecs png_encode {settings}", True, both,
                   "imagecodecs:png_encode", _png_bytes, current=True)]
    c += [Candidate("Pillow PNG", f"compress_level={lv}, optimize=False", True, both, "PIL",
                    _pillow("PNG", compress_level=lv, optimize=False)) for lv in (0, 1, 2, 6)]
    c += [Candidate("Pillow PNG", "compress_level=1, compress_type=3 (Z_RLE)", True, both, "PIL",
                    _pillow("PNG", compress_level=1, compress_type=3))]
    c += [Candidate("OpenCV PNG", "defaults (no params)", True, both, "cv2", _cv2_png())]
    for st in ("", "RLE", "FILTERED", "HUFFMAN_ONLY"):  # "": zlib's default strategy
        strategy = {"IMWRITE_PNG_STRATEGY": f"IMWRITE_PNG_STRATEGY_{st}"} if st else {}
        c.append(Candidate("OpenCV PNG", "COMPRESSION=1" + (f", STRATEGY={st}" if st else ""), True, both, "cv2",
                           _cv2_png(IMWRITE_PNG_COMPRESSION=1, **strategy)))
    c += [Candidate("imagecodecs png (libpng)", "level=1", True, both, "imagecodecs:png_encode",
                    _call("imagecodecs", "png_encode", level=1)),
          Candidate("imagecodecs png (libpng)", "level=1, strategy=RLE, filter=SUB", True, both,
                    "imagecodecs:png_encode", _call("imagecodecs", "png_encode", level=1, strategy=3, filter=16)),
          Candidate("imagecodecs apng (libpng-apng)", "level=1, strategy=RLE, filter=SUB", True, both,
                    "imagecodecs:apng_encode", _call("imagecodecs", "apng_encode", level=1, strategy=3, filter=16)),
          Candidate("imagecodecs spng (libspng)", "level=1", True, both, "imagecodecs:spng_encode",
                    _call("imagecodecs", "spng_encode", level=1)),
          Candidate("pyspng (libspng)", "defaults", True, both, "pyspng:encode", _call("pyspng", "encode")),
          Candidate("fpng", "from_ndarray, defaults", True, rgb, "fpng", _call("fpng", "from_ndarray"))]
    c += [Candidate(f"PNG, SUB rows + {name}", f"level={lv}", True, both, f"imagecodecs:{codec}_encode",
                    _sub_png(codec, lv)) for codec, name in (("zlibng", "zlib-ng"), ("deflate", "libdeflate"))
          for lv in (1, 2, 3)]
    c += [Candidate("Pillow JPEG", f"quality={q}, subsampling=4:4:4", False, rgb, "PIL",
                    _pillow("JPEG", quality=q, subsampling=0)) for q in (95, 90)]
    c += [Candidate("simplejpeg JPEG", f"quality={q}, colorsubsampling=444", False, rgb, "simplejpeg",
                    _call("simplejpeg", "encode_jpeg", quality=q, colorsubsampling="444")) for q in (95, 90)]
    return c


def unavailable(needs: str) -> str | None:
    """None if `needs` ("module" or "module:attribute") imports, else why not."""
    module, _, attr = needs.partition(":")
    try:
        mod = importlib.import_module(module)
    except ImportError:
        return "not installed"
    if attr and not hasattr(mod, attr):
        return f"installed {module} has no {attr}"
    return None


def decode_pillow(data: bytes) -> np.ndarray:
    """The image as Pillow reads it: (h, w, 3) uint8 or (h, w) uint16."""
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im)


def _row(c: Candidate, kind: str, status: str) -> dict:
    return {**dict.fromkeys(ROW_FIELDS), "image": kind, "encoder": c.encoder, "settings": c.settings,
            "lossless": c.lossless, "status": status}


def _fidelity(c: Candidate, kind: str, frames: list[np.ndarray]) -> dict:
    """One untimed encode of every frame: size, exactness, errors (8-bit levels for rgb8, depth units for depth16)."""
    sizes, exact, max_err, abs_sum = [], True, 0, 0.0
    for f in frames:
        data = c.encode(f)
        back = decode_pillow(data)
        assert back.shape == f.shape, f"{c.encoder} ({c.settings}) decodes {f.shape} as {back.shape}"
        same = np.array_equal(back, f)
        assert same or not c.lossless, f"{c.encoder} ({c.settings}) is not lossless on {kind} {f.shape} {f.dtype}"
        err = np.abs(back.astype(np.int64) - f.astype(np.int64))
        exact &= same
        max_err = max(max_err, int(err.max()))
        abs_sum += float(err.mean())
        sizes.append(len(data))
    row = _row(c, kind, "ok")
    row.update(bytes_per_frame=round(statistics.mean(sizes)), exact=exact, max_abs_error=max_err,
               mean_abs_error=round(abs_sum / len(frames), 4),
               compression_ratio=round(frames[0].nbytes / statistics.mean(sizes), 3))
    return row


def thread_speedup(encode: Callable[[np.ndarray], bytes], work: list[np.ndarray], repeats: int = 5) -> float:
    """Wall time of encoding `work` in 1 thread / in 2 threads, each the fastest of `repeats` alternating runs
    (other load only adds time): ~2 if the encoder releases the GIL and both cores are free, ~1 if it holds it."""
    best = {1: float("inf"), 2: float("inf")}
    for r in range(repeats):
        for n in (1, 2) if r % 2 == 0 else (2, 1):
            with ThreadPoolExecutor(n) as pool:
                t = time.perf_counter()
                list(pool.map(encode, work))
                best[n] = min(best[n], time.perf_counter() - t)
    return round(best[1] / best[2], 2)


def measure(cands: list[Candidate], images: dict[str, list[np.ndarray]], rounds: int = 3,
            thread_seconds: float = THREAD_SECONDS) -> list[dict]:
    """A row per (candidate, image kind): fidelity first, then `rounds` interleaved timed rounds (order reversed
    every other round), ms_per_frame the median over frames and rounds, then the 2-thread speedup on the frames
    repeated to at least 2 each and about `thread_seconds` of one-thread work."""
    rows, live = [], []
    for c in cands:
        for kind, frames in images.items():
            if kind not in c.kinds:
                if c.lossless:
                    rows.append(_row(c, kind, f"does not encode {kind}"))
                continue
            reason = unavailable(c.needs)
            if reason is not None:
                rows.append(_row(c, kind, reason))
                continue
            frames = [np.ascontiguousarray(f) for f in frames]
            rows.append(_fidelity(c, kind, frames))
            live.append((rows[-1], c, frames, []))
    for r in range(rounds):
        for row, c, frames, times in live if r % 2 == 0 else live[::-1]:
            for f in frames:
                t = time.perf_counter()
                c.encode(f)
                times.append(time.perf_counter() - t)
    for row, c, frames, times in live:
        row["ms_per_frame"] = round(statistics.median(times) * 1e3, 3)
        copies = max(2, math.ceil(thread_seconds / (statistics.median(times) * len(frames))))
        row["threads2_speedup"] = thread_speedup(c.encode, frames * copies)
    for row, c, _, _ in live:
        base = next((b for b, bc, _, _ in live if bc.current and b["image"] == row["image"]), None)
        if base is not None:
            row["speedup_vs_current"] = round(base["ms_per_frame"] / row["ms_per_frame"], 2)
    return rows


def versions() -> dict[str, str]:
    out = {}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = "not installed"
    from PIL import features  # Pillow's PNG speed depends on which zlib its wheel bundles

    ng = "zlib_ng" in features.features and features.check_feature("zlib_ng")
    out["Pillow's zlib"] = f"zlib-ng {features.version('zlib_ng')}" if ng else f"zlib {features.version('zlib')}"
    return out


def format_table(result: dict) -> str:
    w, h = result["resolution"]
    lines = [f"# Image encoders: {result['spec']} at {w}x{h}, {result['frames']} frames, {result['rounds']} rounds",
             "", f"machine: {result['machine']}  ", f"GL renderer: {result['gl_renderer']}  ",
             "versions: " + ", ".join(f"{k} {v}" for k, v in result["versions"].items()) + "  ",
             "1-minute load average before and after the measurements: "
             + " / ".join(map(str, result.get("load_average_1min", ["n/a"]))), "",
             "ms: median over frames and interleaved rounds, one thread. x current: seasynth.worker.frame.function.png_bytes ms / this "
             f"ms. 2 threads: wall time of >= {THREAD_SECONDS} s of frames in 1 thread / in 2, fastest of 5 each (~2: "
             "releases the GIL and both cores are free; ~1: holds it). "
             "exact: Pillow decodes the very same array. Errors in 8-bit levels (depth16: 1/256 m)."]
    sections = [("rgb8", True, "Lossless, image_2 RGB (h, w, 3) uint8"),
                ("depth16", True, "Lossless, depth (h, w) uint16"),
                ("rgb8", False, "LOSSY (not KITTI PNG; for reference only), image_2 RGB (h, w, 3) uint8")]
    for kind, lossless, title in sections:
        rows = [r for r in result["rows"] if r["image"] == kind and r["lossless"] == lossless]
        rows.sort(key=lambda r: (r["ms_per_frame"] is None, r["ms_per_frame"] or 0))
        lines += ["", f"## {title}", "", "| encoder | settings | ms/frame | x current | KiB/frame | ratio | exact "
                  "| 2 threads | max err | mean err |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            if r["status"] != "ok":
                lines.append(f"| {r['encoder']} | {r['settings']} | {r['status']} | | | | | | | |")
                continue
            lines.append(f"| {r['encoder']} | {r['settings']} | {r['ms_per_frame']:.2f} | "
                         f"{'' if r['speedup_vs_current'] is None else format(r['speedup_vs_current'], '.2f')} | "
                         f"{r['bytes_per_frame'] / 1024:.0f} | {r['compression_ratio']:.2f} | "
                         f"{'yes' if r['exact'] else 'no'} | {r['threads2_speedup']:.2f} | {r['max_abs_error']} | "
                         f"{r['mean_abs_error']} |")
    return "\n".join(lines)


def write_results(result: dict, out: Path) -> str:
    """Write out/encoders.json and out/encoders.md; return the table."""
    table = format_table(result)
    out.mkdir(parents=True, exist_ok=True)
    (out / "encoders.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "encoders.md").write_text(table + "\n")
    return table


def render_frames(spec_path: Path, width: int, height: int, frames: int, platform: str = "egl"):
    """({"rgb8": [(h, w, 3) uint8], "depth16": [(h, w) uint16]}, GL renderer name) of frames 0..frames-1."""
    from seasynth.service.spec.dataset import load_spec
    from seasynth.worker.frame.function import RenderSession

    spec = load_spec(spec_path, {"outputs.depth": True, "outputs.labels": False, "outputs.meta": False,
                                 "camera.width": width, "camera.height": height})
    images: dict[str, list[np.ndarray]] = {k: [] for k in KINDS}
    with RenderSession(platform=platform) as session:
        for i in range(frames):
            files = session.frame_files(spec, i)
            for prefix, kind in (("image_2/", "rgb8"), ("depth/", "depth16")):
                images[kind] += [decode_pillow(b) for k, b in files.items() if k.startswith(prefix)]
        renderer = session.renderer_name
    for kind, want in (("rgb8", (np.uint8, (height, width, 3))), ("depth16", (np.uint16, (height, width)))):
        assert all(a.dtype == want[0] and a.shape == want[1] for a in images[kind]), kind
    return images, renderer


def main(argv: list[str] | None = None) -> None:
    from seasynth.bench.throughput import machine_description

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="folder for encoders.md and encoders.json")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--frames", type=int, default=6)
    p.add_argument("--rounds", type=int, default=3, help="interleaved timed rounds")
    p.add_argument("--spec", type=Path, default=EXAMPLE)
    p.add_argument("--platform", default="egl", help="PyOpenGL platform of the renderer")
    args = p.parse_args(argv)
    images, renderer = render_frames(args.spec, args.width, args.height, args.frames, args.platform)
    spec = args.spec.resolve()
    result = {"machine": machine_description(), "gl_renderer": renderer,
              "spec": str(spec.relative_to(EXAMPLE.parents[1]) if spec.is_relative_to(EXAMPLE.parents[1]) else spec),
              "resolution": [args.width, args.height], "frames": args.frames, "rounds": args.rounds,
              "versions": versions()}
    load_before = os.getloadavg()[0]  # other processes on the machine: the 2-thread speedup needs free cores
    result["rows"] = measure(candidates(), images, args.rounds)
    result["load_average_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    print(write_results(result, args.out))


if __name__ == "__main__":
    main()
