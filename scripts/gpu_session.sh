#!/usr/bin/env bash
# The GPU checks of a session lent a GPU machine (device tool). A session has 15 minutes of device time, the
# machine's start included: one call of under 10 minutes. Prepare here, once: `bash scripts/gpu_wheels.sh` (the
# packages the machine's image lacks, into .whl/), then call the device tool's run with
#   command: bash scripts/gpu_session.sh measure     carry: [".whl", ".gl"]     timeout_s: 600
# (or `session`: the GPU tests and the measure part's tables in one call) and the other parts in later sessions, in
# this order:
# measure:    `python run.py env=ant`'s update path, one seed of TD3X's default of a long run (the hooks compiled
#             inside torch.compile's CUDA graphs) and of cuda_graph=True (gradient_step captured whole) against SB3's
#             and SBX's TD3 (Ant-v5, HalfCheetah-v5), and 16 Ant seeds every way (one SeedBatch, TD3X and SBX
#             processes, with and without MPS; one SB3 process).
# suite:      the whole test suite on the GPU machine (device "auto" is CUDA there), W&B tests left out.
# tests_cuda: the GPU test layer and the tests that name CUDA, graphs or seed batches (a shorter check).
# seeds16:    16 Ant seeds every way with SB3's processes too (the measure part leaves them out for time).
# sb3_seeds:  16 separate SB3 processes on the GPU.
# seeds16_sbx: the 16-seed table with SBX beside (MPS on and off), then tests/gpu.
# nomps_probe: 16 TD3X processes without MPS, three updates (why SBX's led there), and SBX's beside.
# first, last: a session's measure at its start and at its end within its 15 minutes (two calls: `first` at the start,
#             about 4 minutes with the machine's start; `last` after the session's changes, about 9): Ant-v5's
#             one-seed table (TD3X's default of a long run against SB3's and SBX's TD3), and in `last` the whole suite
#             first (cut at 280 s; each test's outcome named as it ends). The 16-seed table does not fit beside them.
# Durations on an H100 (2026-11-27), for planning a call: 16 SBX processes about 150 s per measurement (16 JAX starts
# and compilations), 16 TD3X processes about 60 s, one SB3 process about 20 s, a fresh machine's start about 70 s; one
# SeedBatch of 16 seeds did not finish within 112 s. So one call holds the 16-seed table with SBX (seeds16_sbx) or
# the one-seed tables, not both.
# Everything goes to $OUT (at most 8 files come back). Each step has its own time limit, so that a slow one does not
# take the others' results with it. Runs: 2026-11-23 (H100), 2026-11-25/26 (H200), 2026-11-27 (H100, twice; docs/performance.md).
set -uo pipefail
cd "$(dirname "$0")/.."
part=${1:-measure}
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
start=$SECONDS
if [ ! -d /tmp/site/sb3_td3x_wheels_done ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    > "$OUT/machine.txt" 2>&1 || { cat "$OUT/machine.txt"; echo "install failed"; exit 1; }
  mkdir -p /tmp/site/sb3_td3x_wheels_done
fi
# EGL for MuJoCo (its import fails under MUJOCO_GL=egl without libEGL, which the image lacks): the .debs the device
# README names, downloaded here into the git-excluded .gl/ (see scripts/gpu_wheels.sh) and carried.
if ls .gl/*.deb > /dev/null 2>&1; then for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; fi
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl PYTHONUNBUFFERED=1
{ nvidia-smi; lscpu | grep -E "Model name|^CPU\(s\)"; git log -1 --format="commit %H %s" 2>/dev/null
  python3 -c "import torch, sys; print(sys.version, torch.__version__, torch.cuda.get_device_name())"; } \
  >> "$OUT/machine.txt" 2>&1
left() { echo $(( ${1} - (SECONDS - start) )); }  # seconds left of this part's budget

# The one-seed and 16-seed tables, each command cut at a deadline (seconds from this part's start; $1 is the run.py
# line's own limit, then the deadlines of the two throughput calls and the two 16-seed calls, then extra modes for the
# 16 seeds without MPS), so that a slow one does not take the others' results with it:
# 0. `python run.py env=ant`'s update line on the GPU (a short run: 10k random steps, then 300 gradient steps, so
#    eager; the folder stays in /tmp), first in throughput.txt (at most 8 files come back).
# 1. One seed: TD3X's default of a long run (auto: the compiled update in torch.compile's CUDA graphs), then
#    cuda_graph=True (gradient_step captured whole), each against SB3's and SBX's TD3 in one process, chunks alternated.
# 2. Sixteen Ant seeds: 16 TD3X and 16 SBX processes under CUDA MPS and one SeedBatch (pi(s) batched, the seeds in
#    turn); then the processes without MPS. One SB3 process is each call's baseline. Each measurement's line is
#    printed as it ends (a call cut by its time limit keeps the lines before).
tables() {
  local ant_limit=$1 default_end=$2 graph_end=$3 mps_on_end=$4 mps_off_end=$5 mps_off_extra=${6:-} sbx="" mps budget
  timeout "$ant_limit" python3 run.py env=ant total_timesteps=10300 eval.freq=100000 logger=none progress_bar=false \
    run_dir=/tmp/ant_default > /tmp/ant_default.txt 2>&1
  echo "run.py env=ant rc=$?; $(grep -o 'update: [a-z_]* ([^;]*' /tmp/ant_default.txt | head -1)" > "$OUT/throughput.txt"
  timeout "$(left "$default_end")" python3 benchmarks/throughput.py --env Ant-v5 HalfCheetah-v5 --chunks 2 \
    --chunk-steps 1000 --warmup 1500 --json "$OUT/throughput_graph.json" >> "$OUT/throughput.txt" 2>&1
  echo "throughput default (compiled in CUDA graphs) rc=$?" >> "$OUT/throughput.txt"
  timeout "$(left "$graph_end")" python3 benchmarks/throughput.py --env Ant-v5 HalfCheetah-v5 --chunks 2 \
    --chunk-steps 1000 --warmup 1500 --td3x cuda_graph=true --json "$OUT/throughput.json" >> "$OUT/throughput.txt" 2>&1
  echo "throughput cuda_graph=true rc=$?" >> "$OUT/throughput.txt"
  python3 -c "import sbx" 2>/dev/null && sbx="sbx_procs"
  for mps in on off; do
    budget=$(left "$([ $mps = on ] && echo "$mps_on_end" || echo "$mps_off_end")")
    # shellcheck disable=SC2046,SC2086  # the modes are words
    timeout $(( budget > 30 ? budget : 30 )) python3 benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 \
      --device cuda --seeds 16 --steps 200 --warmup 100 --learning-starts 500 --json "$OUT/seeds16_mps_$mps.json" \
      --mps $mps --modes td3x_procs $sbx $([ $mps = on ] && echo batched || echo "$mps_off_extra") \
      >> "$OUT/seeds16_mps.txt" 2>&1
    echo "seeds16 mps=$mps rc=$?" >> "$OUT/seeds16_mps.txt"
  done
  tail -n 30 "$OUT"/throughput.txt; grep -E "N=|rc=" "$OUT"/seeds16_mps.txt
}

# `first` and `last`'s table, about 150 s: Ant-v5, one seed, TD3X's default of a long run, SB3's and SBX's TD3.
one_seed_table() {  # $1: first or last, in the file names
  timeout 150 python3 benchmarks/throughput.py --env Ant-v5 --chunks 2 --chunk-steps 1000 --warmup 1500 \
    --json "$OUT/throughput_$1.json" > "$OUT/throughput_$1.txt" 2>&1
  echo "throughput Ant-v5 ($1) rc=$? at ${SECONDS}s" >> "$OUT/throughput_$1.txt"
  tail -n 20 "$OUT/throughput_$1.txt"
}

if [ "$part" = first ]; then
  one_seed_table first
elif [ "$part" = last ]; then
  # Cut at 280 s (pytest-xdist prints no summary when stopped): -v names each test's outcome as it ends, counted here.
  timeout -k 10 280 python3 -m pytest -v -p no:cacheprovider -n 14 --timeout 200 -rfEs --durations=10 \
    -k "not wandb" tests > "$OUT/suite.txt" 2>&1
  echo "suite rc=$? at ${SECONDS}s; by outcome: $(grep -oE '\] (PASSED|FAILED|SKIPPED|ERROR)' "$OUT/suite.txt" \
    | sort | uniq -c | tr -s ' \n' ' ')" >> "$OUT/suite.txt"
  grep -E "FAILED|ERROR|rc=" "$OUT/suite.txt" | tail -n 20; tail -n 3 "$OUT/suite.txt"
  one_seed_table last
elif [ "$part" = session ]; then
  # One session's whole check in one call of under 10 minutes: the GPU test layer first (the exactness of the CUDA
  # paths: the default of a long run compiled inside CUDA graphs, SB3 equality, seed batches), then the tables.
  timeout 150 python3 -m pytest -q -p no:cacheprovider -n 11 --timeout 140 -rfEs --durations=12 tests/gpu \
    > "$OUT/tests_gpu.txt" 2>&1
  echo "tests/gpu rc=$?" >> "$OUT/tests_gpu.txt"; tail -n 16 "$OUT/tests_gpu.txt"
  tables 50 330 420 505 585
elif [ "$part" = measure ]; then
  # The tables alone, in one call of under 10 minutes (a session's 15 minutes of device time hold one), the batch
  # also collecting in 16 threads without MPS.
  tables 75 185 285 480 570 batched_threads
elif [ "$part" = tests_cuda ]; then
  # The GPU test layer, then every test that names CUDA, a device or graphs.
  timeout 300 python3 -m pytest -q -p no:cacheprovider -n 6 --timeout 160 -rs tests/gpu \
    tests/unit/test_acceleration.py tests/drop_in/test_drop_in_predict.py tests/drop_in/test_drop_in_save_load.py \
    tests/equivalence/test_seed_batch.py > "$OUT/tests_cuda.txt" 2>&1
  echo "tests_cuda rc=$?" >> "$OUT/tests_cuda.txt"
  tail -n 20 "$OUT"/tests_cuda.txt
elif [ "$part" = seeds16 ]; then
  # Issue 35's 16-seed table: every way of training 16 Ant seeds on the machine, the separate processes with and
  # without CUDA MPS (benchmarks/seeds_scaling.py --mps both); SBX's processes where sbx-rl imports (its wheels,
  # flax, optax and tfp-nightly, are among .whl/'s since scripts/gpu_wheels.sh fetches them; untried on the GPU image).
  modes="batched td3x_procs sb3_procs"
  python3 -c "import sbx" 2>/dev/null && modes="$modes sbx_procs"
  timeout 560 python3 benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 16 \
    --modes $modes --mps both --steps 300 --warmup 100 --json "$OUT/seeds16_mps.json" > "$OUT/seeds16_mps.txt" 2>&1
  echo "seeds16 rc=$?" >> "$OUT/seeds16_mps.txt"
  tail -n 14 "$OUT/seeds16_mps.txt"
elif [ "$part" = seeds16_sbx ]; then
  # The 16-seed table with SBX beside: 16 Ant seeds as 16 TD3X and 16 SBX processes, under MPS and without (one
  # seeds_scaling.py call each, each with its own limit and JSON and its own SB3 process as baseline; 2026-11-27's
  # limits of 170 s cut the TD3X processes after SBX's, so TD3X now goes first), then the GPU test layer.
  python3 -c "import sbx" 2>/dev/null || echo "sbx does not import" >> "$OUT/seeds16_sbx.txt"
  for mps in on off; do
    timeout 250 python3 benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 16 \
      --modes td3x_procs sbx_procs --mps $mps --steps 200 --warmup 100 --learning-starts 500 \
      --json "$OUT/seeds16_sbx_mps_$mps.json" >> "$OUT/seeds16_sbx.txt" 2>&1
    echo "seeds16 sbx mps=$mps rc=$? at ${SECONDS}s" >> "$OUT/seeds16_sbx.txt"
  done
  timeout $(( 585 - SECONDS > 30 ? 585 - SECONDS : 30 )) python3 -m pytest -q -p no:cacheprovider -n 14 --timeout 100 \
    -rfEs --durations=8 tests/gpu > "$OUT/tests_gpu.txt" 2>&1
  echo "tests/gpu rc=$? at ${SECONDS}s" >> "$OUT/tests_gpu.txt"
  grep -E "N=|rc=|sbx" "$OUT/seeds16_sbx.txt"; tail -n 12 "$OUT/tests_gpu.txt"
elif [ "$part" = nomps_probe ]; then
  # Why SBX's 16 processes led TD3X's without MPS on 2026-11-27 (0.79x; 1.82x under MPS). The guess to test (log,
  # "16 seeds against SBX's processes"): a TD3X step submits more separate pieces of GPU work, each waiting for its
  # time slice. 16 TD3X processes without MPS: the default (compiled in CUDA graphs), the whole gradient step captured
  # (cuda_graph=true: sampling too, one replay) and the eager hooks (the most submissions); then SBX's, on the same
  # machine. Each call has its own SB3 process; the last line of each is its rate.
  n=0
  for td3x in "" "cuda_graph=true" "compile_update=false cuda_graph=false"; do
    n=$((n + 1))
    # shellcheck disable=SC2086  # the options are words
    timeout $(( 110 * n + 40 - SECONDS > 40 ? 110 * n + 40 - SECONDS : 40 )) python3 benchmarks/seeds_scaling.py \
      --env Ant-v5 --batch-size 256 --device cuda --seeds 16 --modes td3x_procs --mps off --steps 200 --warmup 100 \
      --learning-starts 500 ${td3x:+--td3x $td3x} --json "$OUT/nomps_td3x_$n.json" >> "$OUT/nomps_probe.txt" 2>&1
    echo "td3x_procs no MPS ${td3x:-default} rc=$? at ${SECONDS}s" >> "$OUT/nomps_probe.txt"
  done
  timeout $(( 585 - SECONDS > 40 ? 585 - SECONDS : 40 )) python3 benchmarks/seeds_scaling.py --env Ant-v5 \
    --batch-size 256 --device cuda --seeds 16 --modes sbx_procs --mps off --steps 200 --warmup 100 \
    --learning-starts 500 --json "$OUT/nomps_sbx.json" >> "$OUT/nomps_probe.txt" 2>&1
  echo "sbx_procs no MPS rc=$? at ${SECONDS}s" >> "$OUT/nomps_probe.txt"
  grep -E "N=|rc=|TD3X with" "$OUT/nomps_probe.txt"
elif [ "$part" = sb3_seeds ]; then
  # The baseline the measure part's time limit cut off: 16 separate SB3 processes (N=1 and 4 are in its table).
  timeout 200 python3 benchmarks/seeds_scaling.py --env Ant-v5 --batch-size 256 --device cuda --seeds 16 \
    --modes sb3_procs --steps 200 --warmup 100 --json "$OUT/seeds_sb3_16.json" > "$OUT/seeds_sb3_16.txt" 2>&1
  echo "seeds rc=$?" >> "$OUT/seeds_sb3_16.txt"
  tail -n 8 "$OUT/seeds_sb3_16.txt"
else
  # The whole suite, as CI runs it but on the GPU machine; W&B tests left out (no wandb wheel carried).
  timeout 470 python3 -m pytest -q -p no:cacheprovider -n 14 --timeout 300 -rfEs --durations=10 -k "not wandb" tests \
    > "$OUT/suite.txt" 2>&1
  echo "suite rc=$?" >> "$OUT/suite.txt"
  # run.py on the GPU, compiled in CUDA graphs (compile_update=true), killed halfway and resumed; the update line says why.
  { timeout 60 python3 run.py debug=smoke env=hopper logger=tensorboard progress_bar=false algo.compile_update=true \
      run_dir=/tmp/cuda_graph_run total_timesteps=3000 checkpoint.freq=1000 & pid=$!; sleep 40; kill -TERM $pid
    wait $pid; echo "run.py cuda_graph stopped rc=$?"
    timeout 120 python3 run.py resume=/tmp/cuda_graph_run; echo "run.py cuda_graph resumed rc=$?"
    tail -n 3 /tmp/cuda_graph_run/evaluations.csv; grep -h "update:" /tmp/cuda_graph_run/run.log | tail -n 1; } \
    >> "$OUT/suite.txt" 2>&1
  tail -n 60 "$OUT/suite.txt"
fi
