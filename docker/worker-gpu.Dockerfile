# syntax=docker/dockerfile:1
# seasynth render worker, NVIDIA GPU: headless OpenGL through the NVIDIA driver's EGL.
# The driver itself (libEGL_nvidia.so.0 and friends) is mounted at run time by the NVIDIA
# container toolkit when the container asks for the `graphics` driver capability; the
# image carries only libglvnd, the vendor-neutral dispatch layer.
#   docker build -f docker/worker-gpu.Dockerfile -t seasynth-worker-gpu .
#   docker run --gpus 'all,"capabilities=compute,utility,graphics"' seasynth-worker-gpu
# SEASYNTH_GPUS=auto: the worker's render processes are spread over every GPU the container sees, pool process k
# on the k-th round robin (one GPU seen: all on it). SEASYNTH_GPUS=N, instead binds them all to EGL device N.

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY pyproject.toml setup.py constraints.txt README.md ./
COPY service ./service
COPY cli ./cli
COPY worker ./worker
RUN pip install -c constraints.txt ".[worker]"

FROM python:3.11-slim
# libglvnd; glvnd's EGL vendor file for the NVIDIA driver (the toolkit may mount the same file); the user the
# worker runs as and its shader cache (below). One layer: under Docker's vfs driver each layer is a whole copy.
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      libglvnd0 libegl1 libgl1 libglx0 libopengl0 libgles2 \
 && rm -rf /var/lib/apt/lists/* \
 && mkdir -p /usr/share/glvnd/egl_vendor.d \
 && printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "libEGL_nvidia.so.0"}}\n' \
      > /usr/share/glvnd/egl_vendor.d/10_nvidia.json \
 && groupadd --system --gid 10001 seasynth \
 && useradd --system --uid 10001 --gid 10001 --create-home --home-dir /home/seasynth seasynth \
 && mkdir -p /var/cache/seasynth/gl /var/cache/seasynth/build \
 && chown 10001:10001 /var/cache/seasynth/gl /var/cache/seasynth/build
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYOPENGL_PLATFORM=egl \
    PYGLET_HEADLESS=1 \
    REMAP_SIGTERM=SIGQUIT \
    __EGL_VENDOR_LIBRARY_FILENAMES=/usr/share/glvnd/egl_vendor.d/10_nvidia.json \
    NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility,graphics \
    SEASYNTH_GPUS=auto \
    __GL_SHADER_DISK_CACHE_PATH=/var/cache/seasynth/gl \
    __GL_SHADER_DISK_CACHE_SIZE=134217728 \
    SEASYNTH_CACHE_DIR=/var/cache/seasynth/build
# The driver's compiled shaders live in __GL_SHADER_DISK_CACHE_PATH: mount a volume there (compose and the
# Kubernetes manifests do) so a restarted worker finds them. On an H100 host a fresh cache made each render
# process's first frame about 0.4 s slower (median 817-930 ms against 473-524; bench/results/gpu/shader-cache.md).
# The driver keeps the cache under __GL_SHADER_DISK_CACHE_SIZE (128 MiB; the example's shaders took 3.6 MB),
# below the Kubernetes volume's 256 MiB limit. SEASYNTH_CACHE_DIR: what the render processes build once, as in
# worker.Dockerfile (compose shares one volume there among the worker containers).
COPY docker/healthcheck.py /usr/local/lib/seasynth/healthcheck.py
# The venv is the last layer with files: under Docker's vfs driver each layer holds a whole copy of the ones
# before it, and a layer after the venv would copy it again.
COPY --from=build /opt/venv /opt/venv
WORKDIR /home/seasynth
USER 10001:10001
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "/usr/local/lib/seasynth/healthcheck.py", "worker"]
# REMAP_SIGTERM=SIGQUIT makes Celery answer SIGTERM with its soft shutdown: running shards get
# SEASYNTH_WORKER_SOFT_SHUTDOWN_S (30 s) to finish, the rest are cancelled and handed back to the
# queue at once. Plain SIGTERM would be a warm shutdown that waits for every shard however long,
# and a kill after the grace period would leave them to the visibility timeout (3x the time limit).
STOPSIGNAL SIGTERM
CMD ["seasynth", "worker"]
