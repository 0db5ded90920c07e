#!/bin/bash
set -u
export PYTHONUNBUFFERED=1 PYGLET_HEADLESS=1 PYOPENGL_PLATFORM=egl
export PYTHONPATH=/tmp/pkg:/tmp/site:/tmp/mi
V=$(ls /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json /usr/share/glvnd/egl_vendor.d/10_nvidia.json 2>/dev/null | head -1)
[ -n "$V" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$V
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
mkdir -p /tmp/mi && tar xJf .mitsuba-cuda.tar.xz -C /tmp/mi || exit 4
mkdir -p /tmp/pkg/seasynth; for r in service worker api bench cli; do ln -sfn $PWD/$r /tmp/pkg/seasynth/$r; done
nvidia-smi -L; nproc
python3 - <<'PY' 2>&1 | tail -3
import mitsuba as mi
mi.set_variant("cuda_ad_rgb")
try:
    d = mi.OptixDenoiser(input_size=[64, 48], albedo=True, normals=True, temporal=False)
    print("optix denoiser: available")
except Exception as e:
    print("optix denoiser: NOT available:", type(e).__name__, str(e)[:300])
PY
timeout 200 bash .diag/pt_rates.sh 256 2>&1 | tee $OUT/pt.log
timeout 280 python3 .diag/transfer_rates.py 2>&1 | grep -v Warning | tee $OUT/train.log
