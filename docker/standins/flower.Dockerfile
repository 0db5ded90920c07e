# Stand-in for mher/flower (docker/standins/build.sh tags it as docker-compose.yml's mher/flower:<tag>): Flower at the
# tag's version from PyPI, with redis, laid out as that image is (user flower, /data, `celery flower`).
ARG BASE=python:3.11-slim
FROM ${BASE}
ARG FLOWER_VERSION
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
COPY constraints.txt /tmp/constraints.txt
# Celery, kombu and redis at the project's pins: what the workers speak (kombu's Redis transport imports packaging).
RUN python -m venv /opt/flower \
 && /opt/flower/bin/pip install -c /tmp/constraints.txt "flower==${FLOWER_VERSION}" redis packaging \
 && rm /tmp/constraints.txt
RUN groupadd --system flower && useradd --system --gid flower --create-home flower \
 && mkdir -p /data && chown flower:flower /data
ENV PATH=/opt/flower/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    FLOWER_DATA_DIR=/data \
    PYTHONPATH=/data
WORKDIR /data
USER flower
VOLUME /data
EXPOSE 5555
CMD ["celery", "flower"]
