"""EGL devices: which ones this machine has, which are GPUs, and the headless platform bound to one of them."""

from __future__ import annotations

import os
from dataclasses import dataclass

from seasynth.service.errors import RenderError
from seasynth.service.gpus import GpuChoice, gpu_for_worker, parse_platform

_EGL_EXTENSIONS = 0x3055  # eglQueryDeviceStringEXT(device, EGL_EXTENSIONS)


@dataclass(frozen=True)
class EglDevice:
    index: int
    extensions: frozenset[str]

    @property
    def is_gpu(self) -> bool:
        """A hardware device: NVIDIA's (EGL_NV_device_cuda) or one with a DRM device (Mesa on AMD/Intel); Mesa's
        software rasteriser (llvmpipe, EGL_MESA_device_software) is not one."""
        if "EGL_MESA_device_software" in self.extensions:
            return False
        return bool({"EGL_NV_device_cuda", "EGL_EXT_device_drm"} & self.extensions)


def prepare_environment(platform: str) -> None:
    """Before OpenGL is first imported: PyOpenGL picks its platform once, at that import."""
    os.environ.setdefault("PYOPENGL_PLATFORM", platform)
    os.environ.setdefault("PYGLET_HEADLESS", "1")
    # NVIDIA's driver waits for the GPU (glFinish, a read-back) by spinning unless told to sleep. With a worker
    # per core, spinning took 17 of 97% of a 16-core H100 host's CPU at 1080p for the same frames/s
    # (bench/results/gpu/scale.md); other drivers ignore the variable.
    os.environ.setdefault("__GL_YIELD", "USLEEP")
    if os.environ["PYOPENGL_PLATFORM"] != platform:
        raise RenderError(
            f"PYOPENGL_PLATFORM is {os.environ['PYOPENGL_PLATFORM']!r} but platform {platform!r} was asked for"
        )


def gl_platform(platform: str, gpu: int | None) -> str:
    """The platform name that binds `gpu` (`egl:N`), or `platform` itself when gpu is None."""
    return platform if gpu is None else f"{parse_platform(platform, gpu)[0]}:{gpu}"


def egl_devices() -> list[EglDevice]:
    """The EGL devices in EGL's order (their index is what `GLRenderer(gpu=...)` takes); [] where EGL cannot list
    devices (no EGL_EXT_device_enumeration)."""
    prepare_environment("egl")
    from pyrender.platforms import egl  # only now: it imports OpenGL, which picks its platform at that import

    try:
        found = egl.query_devices()
    except RuntimeError:  # the enumeration extension is missing: only the default display exists
        return []
    query = egl._eglQueryDeviceStringEXT
    devices = []
    for i, d in enumerate(found):
        text = query(d._display, _EGL_EXTENSIONS) if query is not None else None
        devices.append(EglDevice(i, frozenset((text or b"").decode("ascii", "replace").split())))
    return devices


def gpu_indices() -> list[int]:
    """EGL indices of the devices that are GPUs (what `--gpus auto` spreads over)."""
    return [d.index for d in egl_devices() if d.is_gpu]


def resolve_gpus(choice: GpuChoice | None, platform: str = "egl") -> tuple[int, ...]:
    """The EGL devices `choice` names on this machine; () binds nothing (the default device). Only EGL has
    devices: auto on OSMesa binds nothing, explicit devices there are refused."""
    if choice is None:
        return ()
    if platform != "egl":
        if choice.auto:
            return ()
        raise RenderError(f"GPUs {choice} asked for, but the {platform} platform renders on the CPU; use egl")
    return choice.resolve(gpu_indices())


def egl_platform(gpu: int | None):
    """pyrender's EGLPlatform on EGL device `gpu` (None: EGL's default device); RenderError if there is none."""
    prepare_environment("egl")
    from pyrender.platforms.egl import EGLPlatform, query_devices  # only now, as in egl_devices

    if gpu is None:
        return EGLPlatform(8, 8)
    if gpu < 0:
        raise RenderError(f"GPU device index must be >= 0, got {gpu}")
    try:
        devices = query_devices()
    except RuntimeError as err:  # no EGL_EXT_device_enumeration: no device can be chosen
        raise RenderError(f"GPU device {gpu} asked for, but EGL cannot list devices here ({err})") from err
    if gpu >= len(devices):
        raise RenderError(_no_device(gpu, len(devices)))
    return EGLPlatform(8, 8, device=devices[gpu])


def _no_device(gpu: int, have: int) -> str:
    found = f"{have} device(s) here (indices 0..{have - 1})" if have else "no device here"
    return f"GPU device {gpu} asked for, but EGL finds {found}"


def check_devices(platform: str, gpus: GpuChoice | None) -> None:
    """RenderError now, in this process, where the devices a command names (`egl:N`, `--gpus` indices or a count)
    are not on this machine: before it writes anything. Lists EGL's devices only when a device is named."""
    name, gpu = parse_platform(platform)
    if gpu is not None and gpus is not None:
        raise RenderError(f"GL platform {platform!r} binds one device and --gpus {gpus} spreads over GPUs: give one")
    named = [] if gpus is None or gpus.auto else list(resolve_gpus(gpus, name))  # a count too many raises
    if gpu is not None:
        named.append(gpu)
    if (gpus is not None and gpus.indices is not None) or gpu is not None:
        have = len(egl_devices())
        for index in named:
            if index >= have:
                raise RenderError(_no_device(index, have))


def platform_for_worker(platform: str, gpus: GpuChoice | None, k: int) -> str:
    """The platform name render process k opens its renderer with: `egl:N` for its GPU (the devices of `gpus`
    taken round robin, gpu_for_worker), `platform` unchanged where nothing is bound. Resolving `auto` lists EGL's
    devices, so call this in the render process itself."""
    return gl_platform(platform, gpu_for_worker(k, resolve_gpus(gpus, platform)))
