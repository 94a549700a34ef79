#!/usr/bin/env bash
# Runs (or resumes) the training runs behind docs/results.md, a few at a time, each in a fixed folder
# runs/results/<env>/<algo>/seed<seed>, so that a result can be built over several sittings: run the same command
# again and every unfinished run resumes from its last checkpoint; finished ones are skipped.
#
#   bash scripts/results.sh 200000 hopper:td3:0 hopper:sb3_td3:0 ...   # STEPS then env:algo:seed jobs
#   JOBS=2 bash scripts/results.sh ...                                  # parallel runs (default: one per core)
#   RUN_OVERRIDES="debug=smoke" bash scripts/results.sh ...             # extra run.py overrides for new runs
#
# Stop with Ctrl-C, or `kill -TERM -- -<process group>` when it runs in the background (a background job ignores
# SIGINT, so xargs would go on to the next run): each run checkpoints on SIGINT/SIGTERM before it exits.
set -uo pipefail
cd "$(dirname "$0")/.."
# The project's venv where there is one and PYTHON does not name an interpreter (as scripts/test.sh does).
[ -z "${PYTHON:-}" ] && [ -f .venv/bin/activate ] && . .venv/bin/activate
steps=${1:?usage: bash scripts/results.sh STEPS env:algo:seed [env:algo:seed ...]}
shift
[[ $steps =~ ^[0-9]+$ ]] || { echo "error: STEPS must be a whole number of environment steps, got '$steps'" >&2; exit 2; }
python=${PYTHON:-python}
jobs=${JOBS:-$(nproc)}
root=${RESULTS_DIR:-runs/results}
# The runs side by side share the cores: torch threads per run (one each with the default JOBS).
threads=$(( $(nproc) / jobs > 0 ? $(nproc) / jobs : 1 ))
[[ ${RUN_OVERRIDES:-} == *torch_threads=* ]] && threads_override="" || threads_override="torch_threads=$threads"

one() {
  local job=$1 env algo seed dir
  IFS=: read -r env algo seed <<<"$job"
  if [[ -z $env || -z $algo || ! $seed =~ ^[0-9]+$ ]]; then
    echo "error: job '$job' is not env:algo:seed (e.g. hopper:td3:0)" >&2
    return 2
  fi
  dir=$root/$env/$algo/seed$seed
  if [[ -f $dir/summary.json ]] && "$python" - "$dir/summary.json" "$steps" <<'PY'
import json, sys
sys.exit(0 if json.load(open(sys.argv[1]))["total_timesteps"] >= int(sys.argv[2]) else 1)
PY
  then
    echo "done already: $dir"
    return 0
  fi
  # A run that wrote records but no checkpoint (killed in its first steps) cannot be resumed, and run.py refuses to
  # start a new run over its records: they are moved aside, never deleted, out of the results' folder (where the
  # aggregation would meet the seed twice) to <RESULTS_DIR>.unfinished/<env>/<algo>/seed<seed>-<date>.
  if ! compgen -G "$dir/checkpoints/last*/meta.json" >/dev/null && [[ -f $dir/config.yaml || -f $dir/evaluations.csv ]]; then
    # Unless a process runs in it now, before its first checkpoint (this command started twice): left to it.
    local busy status=0 aside
    busy=$("$python" - "$dir" 2>&1 <<'PY'
import sys
from sb3_td3x.experiment.run.lock import RunFolderBusy, RunFolderLock
try:
    RunFolderLock.check_free(sys.argv[1])
except RunFolderBusy as error:
    print(error)
    sys.exit(3)
PY
    ) || status=$?
    if ((status == 3)); then
      echo "busy, left as it is: $busy"
      return 3
    elif ((status != 0)); then  # fails closed: a folder that may be in use is never moved
      echo "left as it is: $dir has records and no checkpoint, and whether a process runs in it could not be checked" \
        "($python: ${busy##*$'\n'})"
      return 3
    fi
    aside="${root%/}.unfinished/$env/$algo/seed$seed-$(date +%Y%m%d-%H%M%S)"
    mkdir -p "$(dirname "$aside")" && mv "$dir" "$aside" &&
      echo "no checkpoint in $dir: its records moved to $aside, starting again"
  fi
  mkdir -p "$dir"
  # Any checkpoint counts (last, last.prev, a whole last.tmp): run.py takes the newest whole one.
  if compgen -G "$dir/checkpoints/last*/meta.json" >/dev/null; then
    echo "resuming: $dir"
    "$python" run.py resume="$dir" total_timesteps="$steps" progress_bar=false >>"$dir/stdout.log" 2>&1
  else
    echo "starting: $dir"
    # shellcheck disable=SC2086  # RUN_OVERRIDES is a list of words
    "$python" run.py env="$env" algo="$algo" seed="$seed" $threads_override ${RUN_OVERRIDES:-} total_timesteps="$steps" \
      checkpoint.freq=25000 run_dir="$dir" progress_bar=false >>"$dir/stdout.log" 2>&1
  fi
  local rc=$?
  if [[ $rc -eq 0 ]]; then
    echo "exit 0: $dir"
  else  # run.py ends a failure with its reason in one paragraph: the last line of its output
    echo "exit $rc: $dir: $(tail -n 1 "$dir/stdout.log") (the whole output: $dir/stdout.log)"
  fi
  return $rc
}
export -f one
export steps python root threads_override
printf '%s\n' "$@" | xargs -P "$jobs" -I{} bash -c 'one "$1"' _ {}
