#!/usr/bin/env bash
# The GPU checks of a session lent a GPU machine (device tool), in ONE call of under 10 minutes. Untested: written on
# a CPU-only session; the first GPU session should expect to fix it. Prepare here, once: `bash scripts/gpu_wheels.sh`
# (the packages the machine's image lacks, into .whl/), then call the device tool's run with
#   command: bash scripts/gpu_session.sh        carry: [".whl"]        timeout_s: 600
# Everything goes to $OUT (at most 8 files come back): nvidia-smi, the tests, the two benchmarks' JSON and text.
# Each part has its own time limit, so a slow one does not take the others' results with it.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  > "$OUT/install.txt" 2>&1 || { echo "install failed: see install.txt"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl
{ nvidia-smi; python3 -c "import torch, sys; print(sys.version, torch.__version__, torch.cuda.get_device_name())"; } \
  > "$OUT/machine.txt" 2>&1
# 1. The tests that touch CUDA (cuda_graph=True, the device moves, the seeds' CUDA generators), then the rest.
timeout 200 python3 -m pytest -q -p no:cacheprovider -n 8 --timeout 180 -k "cuda or gpu or graph or device" \
  tests/unit tests/equivalence tests/drop_in > "$OUT/tests_cuda.txt" 2>&1
echo "tests_cuda rc=$?" >> "$OUT/tests_cuda.txt"
# 2. TD3X (plain and cuda_graph=True) against SB3's TD3 on the GPU, Ant-v5.
timeout 150 python3 benchmarks/throughput.py --env Ant-v5 --chunks 2 --chunk-steps 1000 --warmup 1000 \
  --json "$OUT/throughput_ant.json" > "$OUT/throughput.txt" 2>&1
timeout 100 python3 benchmarks/throughput.py --env Ant-v5 --chunks 2 --chunk-steps 1000 --warmup 1000 \
  --td3x cuda_graph=true --json "$OUT/throughput_ant_graph.json" >> "$OUT/throughput.txt" 2>&1
# 3. Many seeds: SeedBatch against separate TD3X and SB3 processes, up to 16 seeds.
timeout 120 python3 benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 1 4 16 \
  --modes batched td3x_procs sb3_procs --steps 500 --warmup 200 --json "$OUT/seeds_cuda.json" > "$OUT/seeds.txt" 2>&1
tail -3 "$OUT"/tests_cuda.txt "$OUT"/throughput.txt "$OUT"/seeds.txt
