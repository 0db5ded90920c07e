"""Which GPU each render process uses: the `--gpus` / SEASYNTH_GPUS choice and the process -> device mapping.

Devices are EGL device indices (the order EGL enumerates them, seasynth.worker.render.devices). Which device renders a frame
never changes its bytes on GPUs of one model: a frame depends only on (spec, dataset seed, frame index).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from seasynth.service.errors import RenderError


@dataclass(frozen=True)
class GpuChoice:
    """The GPUs render processes are spread over: the EGL devices `indices`, or the first `count` GPUs found, or
    (neither given: `auto`) every GPU found. Where no GPU is found, auto binds nothing (the default device)."""

    indices: tuple[int, ...] | None = None
    count: int | None = None

    def __post_init__(self) -> None:
        if self.indices is not None and self.count is not None:
            raise ValueError("a GPU choice names either devices or a count, not both")
        if self.count is not None and self.count < 1:
            raise ValueError(f"a GPU count must be >= 1, got {self.count}")
        if self.indices is not None and (not self.indices or min(self.indices) < 0):
            raise ValueError(f"GPU device indices must be >= 0, got {list(self.indices)}")

    @property
    def auto(self) -> bool:
        return self.indices is None and self.count is None

    def resolve(self, found: Sequence[int]) -> tuple[int, ...]:
        """The device indices to spread over, given the indices of the GPUs this machine has (`found`)."""
        if self.indices is not None:
            return self.indices
        if self.count is None:
            return tuple(found)
        if self.count > len(found):
            raise RenderError(f"{self.count} GPUs asked for, but EGL finds {len(found)} GPU device(s) here")
        return tuple(found[: self.count])

    def __str__(self) -> str:
        if self.indices is not None:
            return ",".join(map(str, self.indices)) + ("," if len(self.indices) == 1 else "")
        return "auto" if self.count is None else str(self.count)


def parse_gpus(text: str) -> GpuChoice:
    """`auto`, a count `N` (the first N GPUs found), or EGL device indices `0,1` (one device: `1,`)."""
    t = text.strip().lower()
    try:
        if t == "auto":
            return GpuChoice()
        if "," in t:
            return GpuChoice(indices=tuple(int(v) for v in t.split(",") if v.strip()))
        return GpuChoice(count=int(t))
    except ValueError as err:
        raise ValueError(f"GPUs {text!r}: give auto, a count N, or comma-separated device indices like 0,1 "
                         f"(one device: 1,) ({err})") from None


def gpu_for_worker(k: int, devices: Sequence[int]) -> int | None:
    """The device of render process k (0-based): round robin over `devices`; None (the default device) if empty."""
    if k < 0:
        raise ValueError(f"worker index must be >= 0, got {k}")
    return devices[k % len(devices)] if devices else None


def parse_platform(platform: str, gpu: int | None = None) -> tuple[str, int | None]:
    """("egl" or "osmesa", EGL device index or None) of a platform name, which may name its device as `egl:N`
    (so callers that pass a platform name through, like RenderSession, can bind a GPU)."""
    name, sep, index = platform.partition(":")
    if name not in ("egl", "osmesa"):
        raise RenderError(f"unsupported GL platform {platform!r}; use 'egl', 'egl:N' (EGL device N) or 'osmesa'")
    if sep:
        if name != "egl" or not index.isdigit() or (gpu is not None and gpu != int(index)):
            raise RenderError(f"GL platform {platform!r}: only egl takes a device, as egl:N with N >= 0 "
                              f"(and no other gpu={gpu})")
        gpu = int(index)
    if gpu is not None and name != "egl":
        raise RenderError(f"GPU device {gpu} asked for on the {name} platform, which renders on the CPU; use egl")
    return name, gpu
