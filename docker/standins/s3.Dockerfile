# Stand-ins for MinIO's images (docker/standins/build.sh tags --target minio as docker-compose.yml's minio/minio:<tag>
# and --target mc as its minio/mc:<tag>): moto's S3 server, kept on disk, behind a `minio` entrypoint, and an `mc`
# for the commands compose runs. Both commands are in both images, as mc is in MinIO's server image.
ARG BASE=python:3.11-slim
FROM ${BASE} AS s3
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
COPY constraints.txt /tmp/constraints.txt
# moto's S3 and its server (flask), at the project's pins.
RUN python -m venv /opt/moto \
 && /opt/moto/bin/pip install -c /tmp/constraints.txt "moto[s3]" flask flask-cors \
 && rm /tmp/constraints.txt
COPY docker/standins/s3/minio docker/standins/s3/mc /usr/local/bin/
RUN groupadd --system --gid 1000 minio \
 && useradd --system --uid 1000 --gid 1000 --create-home --home-dir /home/minio minio \
 && mkdir -p /data && chown minio:minio /data
USER minio
WORKDIR /home/minio

FROM s3 AS minio
VOLUME /data
EXPOSE 9000
ENTRYPOINT ["minio"]
CMD ["server", "/data"]

FROM s3 AS mc
ENTRYPOINT ["mc"]
