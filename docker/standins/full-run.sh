#!/usr/bin/env bash
# The compose test at full size, as CI runs it within .ci/run, alone: tests/test_compose.py (stand-in images, the
# api, worker and GPU worker images built, 2 shard workers, a worker SIGKILLed and Redis restarted mid-run, down/up,
# Flower, both /metrics), its timings and results written to bench/results/compose.md (or FILE).
#
#   sudo bash docker/standins/full-run.sh [FILE]      after `bash .ci/setup` (docker.io, docker-compose, debootstrap)
#
# Needs root (dockerd, debootstrap), about 16 GiB free under TMPDIR, the network to Debian's mirror and PyPI, and
# host ports 8000, 9000, 9001 and 5555 free. It starts its own dockerd and removes it, its images and its folder
# at the end.
set -euo pipefail
cd "$(dirname "$0")/../.."
report="${1:-bench/results/compose.md}"
export PYOPENGL_PLATFORM=egl PYGLET_HEADLESS=1 SEASYNTH_COMPOSE=full SEASYNTH_COMPOSE_REPORT="$report"
.venv/bin/python -m pytest -q -p no:cacheprovider -rA tests/test_compose.py
echo "full-run.sh: results in $report"
