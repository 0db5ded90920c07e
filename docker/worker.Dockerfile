# syntax=docker/dockerfile:1
# seasynth render worker, CPU: headless OpenGL through EGL on Mesa's llvmpipe.
#   docker build -f docker/worker.Dockerfile -t seasynth-worker .

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
# Mesa EGL (surfaceless llvmpipe) and the GL dispatch libraries PyOpenGL loads, and the user the worker runs as, in
# one layer (under Docker's vfs driver each layer is a whole copy).
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      libegl1 libgl1 libegl-mesa0 libgles2 libgl1-mesa-dri \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 10001 seasynth \
 && useradd --system --uid 10001 --gid 10001 --create-home --home-dir /home/seasynth seasynth \
 && mkdir -p /var/cache/seasynth/build && chown 10001:10001 /var/cache/seasynth/build
# PYGLET_HEADLESS: pyrender imports pyglet, which needs X libraries unless headless.
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYOPENGL_PLATFORM=egl \
    PYGLET_HEADLESS=1 \
    REMAP_SIGTERM=SIGQUIT \
    SEASYNTH_CACHE_DIR=/var/cache/seasynth/build
# What the render processes build once (terrain variants, texture sets, solved water columns; docs/cli.md) lives in
# SEASYNTH_CACHE_DIR: compose mounts one named volume there for every worker container, so a water's columns are
# solved once for all of them (a lock file makes the others wait and read them) and outlive the containers.
COPY docker/healthcheck.py /usr/local/lib/seasynth/healthcheck.py
# The venv is the last layer with files: under Docker's vfs driver each layer holds a whole copy of the ones
# before it, and a layer after the venv would copy it again.
COPY --from=build /opt/venv /opt/venv
WORKDIR /home/seasynth
USER 10001:10001
# Alive with its prefork pool up (no broker round trip, unlike `celery inspect ping`).
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "/usr/local/lib/seasynth/healthcheck.py", "worker"]
# REMAP_SIGTERM=SIGQUIT makes Celery answer SIGTERM with its soft shutdown: running shards get
# SEASYNTH_WORKER_SOFT_SHUTDOWN_S (30 s) to finish, the rest are cancelled and handed back to the
# queue at once. Plain SIGTERM would be a warm shutdown that waits for every shard however long,
# and a kill after the grace period would leave them to the visibility timeout (3x the time limit).
STOPSIGNAL SIGTERM
CMD ["seasynth", "worker"]
