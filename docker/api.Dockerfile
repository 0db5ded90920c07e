# syntax=docker/dockerfile:1
# seasynth HTTP API. No OpenGL here: the API never imports worker code, and this image
# does not even contain it (only service/ and api/ are copied). Uploads are checked with trimesh
# and Pillow (the `api` extra), which need no OpenGL.
#   docker build -f docker/api.Dockerfile -t seasynth-api .

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
COPY api ./api
RUN pip install -c constraints.txt ".[api]"

FROM python:3.11-slim
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1
RUN groupadd --system --gid 10001 seasynth \
 && useradd --system --uid 10001 --gid 10001 --create-home --home-dir /home/seasynth seasynth
COPY docker/healthcheck.py /usr/local/lib/seasynth/healthcheck.py
# The venv is the last layer with files: under Docker's vfs driver each layer holds a whole copy of the ones
# before it, and a layer after the venv would copy it again.
COPY --from=build /opt/venv /opt/venv
WORKDIR /home/seasynth
USER 10001:10001
EXPOSE 8000
HEALTHCHECK --interval=15s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "/usr/local/lib/seasynth/healthcheck.py", "http", "http://127.0.0.1:8000/healthz"]
STOPSIGNAL SIGTERM
CMD ["seasynth", "serve", "--host", "0.0.0.0", "--port", "8000"]
