#!/bin/bash
# The `gpu` budget's curves on one GPU: the default objective on two seeds and the supervised oracle,
# side by side (CUDA MPS when the machine has it), stopped after MINUTES with a last probe row each,
# then H of the three runs on the first four probe images. PACK: `objective_sweep.py pack --setting
# protocol --height 256 --width 512 ...` (docs/normals_from_shading.md, "The default at the paper's
# resolution").
#   bash bench/gpu_budget.sh PACK MINUTES OUT
# STEPS (default 20000, the budget's schedule; the decay starts halfway) and ORACLE_SEEDS (default 1)
# shorten the schedule and pick the oracle's seeds: STEPS=2700 completes a schedule, decay included,
# within one 10-minute command (7.9 minutes for the three runs on an H100). RUNS (a folder, e.g.
# out/gpu_runs) keeps a run folder per run there: a rerun with the same RUNS goes on from each run's
# last stop, so the whole schedule can be trained in commands of under 10 minutes; OUT then gets
# each run's curve from step 0.
set -u
PACK=$1; MIN=$2; O=$3
STEPS=${STEPS:-20000}; ORACLE_SEEDS=${ORACLE_SEEDS:-1}; RUNS=${RUNS:-}
PY=${PY:-python3}
W=$(mktemp -d)
mkdir -p "$O"
export PYTHONUNBUFFERED=1
if command -v nvidia-cuda-mps-control >/dev/null; then nvidia-cuda-mps-control -d && echo "CUDA MPS on"; fi
G=(bench/objective_sweep.py grid --data "$PACK" --variants bench/variants_gpu.toml --steps "$STEPS" --every 250 --batch 1
   --decay 0.5 --minutes "$MIN" --out "$O" --save-dir "$W" ${RUNS:+--runs-dir "$RUNS"})
$PY "${G[@]}" --only default --seeds 0 1 &
$PY "${G[@]}" --only oracle --seeds $ORACLE_SEEDS &
wait
# a resumed run's OUT file holds this command's rows only; its run folder holds them all
if [ -n "$RUNS" ]; then
  for r in "$RUNS"/*/; do r=${r%/}; [ -f "$r/stats.jsonl" ] && cp "$r/stats.jsonl" "$O/$(basename "$r").jsonl"; done
fi
# the picture builds each model from its variant's --set values, read from the variants file
P=$($PY -c "import sys; sys.path.insert(0, 'bench'); from objective_sweep import load_variants
print(','.join(load_variants('bench/variants_gpu.toml')['default']['set']))")
R=()
for s in 0 1; do [ -f "$W/default_s$s.safetensors" ] && R+=("seed $s=$W/default_s$s.safetensors,$P"); done
for s in $ORACLE_SEEDS; do
  [ -f "$W/oracle_s$s.safetensors" ] && R+=("oracle, seed $s=$W/oracle_s$s.safetensors,model.kind=oracle")
done
[ ${#R[@]} -gt 0 ] && $PY bench/objective_sweep.py picture --data "$PACK" --config paper --samples 4 --scale 1 \
  --out "$O/default_h.jpg" "${R[@]}"
rm -rf "$W"
