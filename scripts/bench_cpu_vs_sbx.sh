#!/usr/bin/env bash
# The CPU tables of docs/performance.md on this machine's CPU: TD3X's defaults against SB3's and SBX's TD3 (throughput.py, one process,
# chunks alternated), many seeds against SBX's separate processes (seeds_scaling.py), and where a step goes
# (step_split.py). The CPU changes between sessions: every output names it. Needs SBX (pip install -e ".[peers]")
# and a quiet machine (nothing else running: no suite, no training, no helper). About 25 minutes on 2 cores.
#
#   bash scripts/bench_cpu_vs_sbx.sh                 # JSON and logs into bench_out/<cpu>_<date>/
#   OUT=somewhere bash scripts/bench_cpu_vs_sbx.sh
set -euo pipefail
cd "$(dirname "$0")/.."
[ -f .venv/bin/activate ] && . .venv/bin/activate
python -c "import sbx" 2>/dev/null || { echo "error: SBX is not installed: pip install -e \".[peers]\"" >&2; exit 2; }
cpu=$(python - <<'EOF'
import re
name = next((l.split(":", 1)[1] for l in open("/proc/cpuinfo") if l.startswith("model name")), "cpu")
print(re.sub(r"[^a-z0-9]+", "_", name.strip().lower()).strip("_"))
EOF
)
out=${OUT:-bench_out/${cpu}_$(date +%Y-%m-%d_%H-%M)}
mkdir -p "$out"
out=$(cd "$out" && pwd)
echo "CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2-), $(nproc) cores; outputs in $out"
lscpu > "$out/lscpu.txt"
git rev-parse HEAD > "$out/commit.txt"
cd benchmarks
run() {  # NAME then the command: its output to NAME.txt, the last lines shown
  local name=$1
  shift
  echo "== $name: $*"
  "$@" > "$out/$name.txt" 2>&1
  grep -v '^USDT' "$out/$name.txt" | tail -n 12
}
run hopper_b100_t2 python throughput.py --env Hopper-v5 --batch-size 100 --threads 2 --chunks 6 --chunk-steps 500 \
  --json "$out/hopper_b100_t2.json"
run ant_b256_t2 python throughput.py --env Ant-v5 --batch-size 256 --threads 2 --chunks 5 --chunk-steps 400 \
  --json "$out/ant_b256_t2.json"
run hopper_b100_t1 python throughput.py --env Hopper-v5 --batch-size 100 --threads 1 --chunks 5 --chunk-steps 500 \
  --json "$out/hopper_b100_t1.json"
run seeds_hopper_b256 python seeds_scaling.py --env Hopper-v5 --batch-size 256 --seeds 2 8 \
  --modes batched batched_per_core td3x_procs sbx_procs --steps 500 --warmup 200 --threads 2 \
  --json "$out/seeds_hopper_b256.json"
run step_split_hopper_b100 python step_split.py --env Hopper-v5 --batch-size 100 --threads 2 --chunks 5 \
  --chunk-steps 500 --json "$out/step_split_hopper_b100.json"
