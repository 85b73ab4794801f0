#!/usr/bin/env bash
# Retrain the shipped rate points on one machine within a wall-clock budget, all of them at once: simulate the
# training set (datasets/sim_mix of the model cards), then train every rate from its shipped weights in its own
# process on the same device, and pack the best checkpoints into OUT/models.tar.
#
#     benchmarks/retrain.sh OUT [MINUTES]          # MINUTES of training per rate, all rates together (default 6)
#
# Environment (defaults in brackets): DEVICE [cuda] cpu or cuda; RATES [e0 e1 e2 e3]; OBJECTIVE [chamfer] or
# mean-distance; ENCODER_ONLY [0] 1 trains the encoder alone (files of the shipped model still decode);
# MAX_LR [3e-4]; SEED [21]; DATASET [simulate into OUT/sim_mix] an existing dataset folder instead;
# SUBMAPS [200] and SPARSE [60] the simulated multi-scan submaps and single 32-beam sweeps; WORKERS [all cores]
# for the simulator, shared among the trainings as OpenMP threads; MAX_STEPS [none] a step cap per rate;
# PYTHON [.venv/bin/python if present, else python3].
#
# Score the result on the CPU afterwards, e.g. for e1:
#     tar -xf OUT/models.tar -C runs/retrained
#     mapsqueeze bench ../shared/data/real/submaps --codecs mapsqueeze --models runs/retrained/e1 -o results/e1_new
#     .venv/bin/python benchmarks/compare_fronts.py results/real_r0/results.csv results/e1_new_front.csv
# (the front CSV as in BENCHMARKS.md, "Against the full classical front").
set -euo pipefail

out=${1:?usage: benchmarks/retrain.sh OUT [MINUTES]}
minutes=${2:-6}
device=${DEVICE:-cuda}
rates=(${RATES:-e0 e1 e2 e3})
objective=${OBJECTIVE:-chamfer}
max_lr=${MAX_LR:-3e-4}
seed=${SEED:-21}
submaps=${SUBMAPS:-200}
sparse=${SPARSE:-60}
workers=${WORKERS:-$(nproc)}
root=$(cd "$(dirname "$0")/.." && pwd)
if [[ -n ${PYTHON:-} ]]; then py=$PYTHON
elif [[ -x $root/.venv/bin/python ]]; then py=$root/.venv/bin/python
else py=python3
fi
export PYTHONPATH=$root/src${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1

"$py" - "$device" <<'EOF'
import sys

import torch

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.model.devices import torch_device

try:
    device = torch_device(sys.argv[1])  # the check train makes, before minutes of simulation
except MapsqueezeError as exc:
    sys.exit(f"error: {exc}; DEVICE=cpu trains on the CPU")
where = torch.cuda.get_device_name(device) if device.type == "cuda" else "the CPU"
print(f"torch {torch.__version__} on {where}")
EOF
mkdir -p "$out"
out=$(cd "$out" && pwd)

if [[ -n ${DATASET:-} ]]; then
    data=$DATASET
else
    data=$out/sim_mix
    start=$(date +%s)
    "$py" -m mapsqueeze simulate -o "$data" --sensor hdl64,hdl64,hdl64,hdl32,vlp32c,os1_128,os2_128 \
        --preset urban,urban,suburban,suburban,rural,highway --submaps "$submaps" --seed 1 --workers "$workers"
    if (( sparse > 0 )); then
        "$py" -m mapsqueeze simulate -o "$data" --sensor hdl32,vlp32c --preset urban,suburban,rural,highway \
            --submaps "$sparse" --scans 1 --seed 3 --split train --workers "$workers"
    fi
    echo "simulated in $(( $(date +%s) - start )) s"
fi

threads=$(( workers / ${#rates[@]} ))
(( threads >= 1 )) || threads=1
extra=()
[[ ${ENCODER_ONLY:-0} == 1 ]] && extra+=(--encoder-only)
[[ -n ${MAX_STEPS:-} ]] && extra+=(--max-steps "$MAX_STEPS")
pids=()
for rate in "${rates[@]}"; do
    OMP_NUM_THREADS=$threads "$py" -m mapsqueeze train "$data" --rate "$rate" -o "$out/$rate" \
        --init "$root/src/mapsqueeze/models/$rate" --device "$device" --objective "$objective" --max-lr "$max_lr" \
        --max-minutes "$minutes" --val-limit 8 --seed "$seed" --no-resume "${extra[@]}" > "$out/$rate.log" 2>&1 &
    pids+=($!)
done
failed=0
for i in "${!rates[@]}"; do
    if ! wait "${pids[$i]}"; then
        echo "error: training ${rates[$i]} failed; the end of $out/${rates[$i]}.log:"
        tail -n 20 "$out/${rates[$i]}.log"
        failed=1
    fi
done

"$py" - "$out" "${rates[@]}" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
for rate in sys.argv[2:]:
    path = out / rate / "summary.json"
    if not path.is_file():
        print(f"{rate}: no summary")
        continue
    s = json.loads(path.read_text())
    best = {k: v for k, v in s.items() if k.startswith("best_") and v is not None}
    print(f"{rate}: {s['steps']} steps in {s['minutes']:.1f} min, {best}")
EOF

best=()
for rate in "${rates[@]}"; do
    [[ -f $out/$rate/best/model.safetensors ]] && best+=("$rate")
done
if (( ${#best[@]} )); then
    # tar names the folders e0 ... e3 (each a model folder: config.json, model.safetensors)
    # written to a temporary name and renamed, so that models.tar is whole or absent
    tar -cf "$out/models.tar.partial" --transform 's,/best,,' -C "$out" "${best[@]/%//best}"
    mv -f "$out/models.tar.partial" "$out/models.tar"
    echo "wrote $out/models.tar: ${best[*]}"
fi
exit $failed
