#!/usr/bin/env bash
# Builds, into the Docker engine at DOCKER_HOST, stand-ins for the third-party images that docker/*.Dockerfile and
# docker-compose.yml name, for a machine that cannot reach Docker Hub. Each is tagged with the exact name the
# project uses, so the real Dockerfiles and compose file run unchanged (with docker/compose.standins.yml, which
# only adds what this engine needs: build on the host network). Needs root (debootstrap), docker and the network
# to Debian's mirror and PyPI.
#
#   python:3.11-slim          Debian bookworm (Python 3.11) from debootstrap --variant=minbase, python3-venv,
#                             ca-certificates; /usr/local/bin/python -> python3; no pip (the Dockerfiles make venvs)
#   redis:<compose's tag>     Debian's redis-server (7.0), started as the official entrypoint does
#   minio/minio:<tag>         moto's S3 server behind a `minio server DIR` entrypoint; objects survive a restart
#                             (every write is recorded under DIR and replayed at start: docker/standins/s3/minio)
#   minio/mc:<tag>            an `mc` for `alias set`, `mb [--ignore-existing]` and `ready` (docker/standins/s3/mc)
#   mher/flower:<tag>         Flower from PyPI at the tag's version, Celery and redis at constraints.txt's pins
#
#   DOCKER_HOST=unix:///path/docker.sock bash docker/standins/build.sh [--force]
#
# Images already present are kept unless --force. Stand-ins are for trying the stack on such a machine only:
# with Docker Hub, compose pulls the real images and this script is not needed.
set -euo pipefail
cd "$(dirname "$0")/../.."

force=0
[[ "${1:-}" == "--force" ]] && force=1
# The classic builder: it needs no image of its own (BuildKit's `# syntax=` frontends come from Docker Hub).
export DOCKER_BUILDKIT=0
SUITE=bookworm  # Debian 12: Python 3.11, the tag's minor version
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"

# The tags, as docker-compose.yml and the Dockerfiles spell them.
compose_image() { sed -n "s|^ *image: *\(${1}:[^ ]*\) *$|\1|p" docker-compose.yml | head -1; }
PYTHON_TAG=$(sed -n 's/^FROM \(python:[^ ]*\).*$/\1/p' docker/api.Dockerfile | head -1)
REDIS_TAG=$(compose_image redis)
MINIO_TAG=$(compose_image minio/minio)
MC_TAG=$(compose_image minio/mc)
FLOWER_TAG=$(compose_image mher/flower)
for t in PYTHON_TAG REDIS_TAG MINIO_TAG MC_TAG FLOWER_TAG; do
  [[ -n "${!t}" ]] || { echo "build.sh: no ${t%_TAG} image in docker-compose.yml or docker/api.Dockerfile" >&2; exit 1; }
done
if [[ "$PYTHON_TAG" != python:3.11-* ]]; then
  echo "build.sh: the base is $PYTHON_TAG; Debian $SUITE gives Python 3.11" >&2
  exit 1
fi

have() { [[ $force -eq 0 ]] && docker image inspect "$1" >/dev/null 2>&1; }
stamp() { echo "build.sh: $(date +%T) $*"; }
elapsed() { echo "build.sh: $1 in $(( SECONDS - $2 )) s"; }

if have "$PYTHON_TAG"; then
  stamp "$PYTHON_TAG present"
else
  t0=$SECONDS
  stamp "$PYTHON_TAG: debootstrap $SUITE from $MIRROR"
  root=$(mktemp -d "${TMPDIR:-/tmp}/seasynth-python-root.XXXXXX")
  trap 'rm -rf "$root"' EXIT
  chmod 755 "$root"  # it becomes the image's /, which every user must be able to enter (mktemp made it 0700)
  debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates "$SUITE" "$root" "$MIRROR" \
    > "$root.log" 2>&1 || { tail -20 "$root.log" >&2; exit 1; }
  rm -f "$root.log"
  # As the official image: python on /usr/local/bin, the suite's updates and security sources, no apt caches.
  ln -sf /usr/bin/python3 "$root/usr/local/bin/python"
  ln -sf /usr/bin/python3 "$root/usr/local/bin/python3"
  cat > "$root/etc/apt/sources.list" <<SOURCES
deb $MIRROR $SUITE main
deb $MIRROR $SUITE-updates main
deb ${MIRROR%/debian}/debian-security $SUITE-security main
SOURCES
  # pip in the images' builds (Debian's pip reads the system bundle) must trust what the host trusts.
  cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/ca-certificates.crt"
  rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/cache/apt/*.bin "$root"/var/lib/apt/lists/* \
    "$root"/usr/share/doc/* "$root"/usr/share/man/*
  tar -C "$root" -c . | docker import \
    -c 'ENV PATH=/usr/local/bin:/usr/local/sbin:/usr/sbin:/usr/bin:/sbin:/bin' -c 'ENV LANG=C.UTF-8' \
    -c 'CMD ["python3"]' -m "stand-in for $PYTHON_TAG: Debian $SUITE minbase (docker/standins/build.sh)" \
    - "$PYTHON_TAG" >/dev/null
  rm -rf "$root"
  trap - EXIT
  elapsed "$PYTHON_TAG" $t0
fi

# The others build on the stand-in base, from the repository root (constraints.txt pins their Python packages).
build() {  # TAG DOCKERFILE [docker build args]
  local tag=$1 file=$2 t0=$SECONDS
  shift 2
  if have "$tag"; then stamp "$tag present"; return; fi
  stamp "$tag: docker build -f $file"
  local log
  log=$(mktemp "${TMPDIR:-/tmp}/seasynth-standin-build.XXXXXX")
  if ! docker build --network host -f "$file" -t "$tag" --build-arg BASE="$PYTHON_TAG" "$@" . > "$log" 2>&1; then
    tail -40 "$log" >&2
    rm -f "$log"
    echo "build.sh: building $tag failed" >&2
    exit 1
  fi
  rm -f "$log"
  elapsed "$tag" $t0
}
build "$REDIS_TAG" docker/standins/redis.Dockerfile
build "$MINIO_TAG" docker/standins/s3.Dockerfile --target minio
build "$MC_TAG" docker/standins/s3.Dockerfile --target mc
build "$FLOWER_TAG" docker/standins/flower.Dockerfile --build-arg FLOWER_VERSION="${FLOWER_TAG##*:}"
stamp "stand-ins ready: $PYTHON_TAG $REDIS_TAG $MINIO_TAG $MC_TAG $FLOWER_TAG"
