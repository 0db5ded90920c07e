#!/bin/bash
# path tracer alone: 4 clear-sun + 4 ocean-sun test images at 320x240, one process per GPU, per spp given
NG=$(python3 -c "import torch; print(torch.cuda.device_count())")
for SPP in "$@"; do
  python3 - $SPP <<'PY'
import json, sys
r = json.load(open("bench/recipes/transfer.json"))
spp = int(sys.argv[1])
r.update(width=320, height=240)
r["test"]["spp"] = spp
r["test"]["groups"] = [dict(g, frames=4) for g in r["test"]["groups"][:2]]
json.dump(r, open(f"/tmp/pt-{spp}.json", "w"))
PY
  T0=$(date +%s)
  for k in $(seq 0 $((NG - 1))); do
    CUDA_VISIBLE_DEVICES=$k python3 -m seasynth.cli bench transfer --work /tmp/pt-$SPP --recipe /tmp/pt-$SPP.json \
      --testset-shard $k/$NG > /tmp/pt-$SPP-$k.log 2>&1 &
  done; wait
  echo "{\"spp\": $SPP, \"gpus\": $NG, \"wall_s\": $(( $(date +%s) - T0 ))}"
  cat /tmp/pt-$SPP-*.log | grep file_name
done
