#!/usr/bin/env bash
# The project's test command (README, and .ci/run on a fresh clone).
#   bash scripts/test.sh            # the whole suite
#   bash scripts/test.sh -k hooks   # extra arguments go to pytest
set -euo pipefail
cd "$(dirname "$0")/.."
[ -f .venv/bin/activate ] && . .venv/bin/activate
export MUJOCO_GL="${MUJOCO_GL:-egl}"
export PYTHONUNBUFFERED=1
export NO_MKDOCS_2_WARNING=1

# PostgreSQL (the many-workers sweep test) and a one-node SLURM (the cluster tests, tests/cluster): started from
# Debian's packages in CI, or when asked for. Their output (apt-get, initdb, the daemons) goes to one log file, shown
# only if a start fails; one line names it.
services_log=""
started=()
start_service() {  # NAME VARIABLE SCRIPT: run SCRIPT, which prints the value of VARIABLE on stdout
  local value
  [ -n "$services_log" ] || services_log="$(mktemp "${TMPDIR:-/tmp}/sb3-td3x-services.XXXXXX")"
  echo "== $3" >>"$services_log"
  if ! value="$(bash "$3" 2>>"$services_log")"; then
    echo "scripts/test.sh: $1 did not start. Its output ($services_log):" >&2
    cat "$services_log" >&2
    exit 1
  fi
  export "$2=$value"
  started+=("$1")
}
if [ -z "${SB3_TD3X_TEST_PG_URL:-}" ] && { [ "${CI:-}" = "true" ] || [ "${SB3_TD3X_START_POSTGRES:-}" = "1" ]; } && [ -f .ci/postgres.sh ]; then
  start_service PostgreSQL SB3_TD3X_TEST_PG_URL .ci/postgres.sh
fi
if [ -z "${SLURM_CONF:-}" ] && { [ "${CI:-}" = "true" ] || [ "${SB3_TD3X_START_SLURM:-}" = "1" ]; } && [ -f .ci/slurm.sh ]; then
  start_service SLURM SLURM_CONF .ci/slurm.sh
fi
if [ "${#started[@]}" -gt 0 ]; then
  names="${started[*]}"
  echo "Started for the tests: ${names// / and } (their output: $services_log)"
fi

# The documentation must build with warnings as errors. (Not --quiet: it hides the warnings from --strict, which
# then passes a broken link.) The build's output is shown only if it fails.
if [ -f mkdocs.yml ]; then
  if ! docs_out="$(mkdocs build --strict --site-dir site 2>&1)"; then
    echo "$docs_out" >&2
    echo "scripts/test.sh: the documentation does not build (mkdocs build --strict)" >&2
    exit 1
  fi
fi

# Two processes for two cores; each test process uses one torch thread (tests/conftest.py).
python -m pytest -n 2 --dist loadfile --timeout 900 -q --durations=15 "$@"
