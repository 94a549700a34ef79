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

# PostgreSQL for the many-workers sweep test: started from Debian's packages in CI (or when asked for).
if [ -z "${SB3_TD3X_TEST_PG_URL:-}" ] && { [ "${CI:-}" = "true" ] || [ "${SB3_TD3X_START_POSTGRES:-}" = "1" ]; } && [ -f .ci/postgres.sh ]; then
  # shellcheck disable=SC1091
  . .ci/postgres.sh
fi

# A one-node SLURM for the cluster tests (tests/cluster): started from Debian's packages in CI (or when asked for).
if [ -z "${SLURM_CONF:-}" ] && { [ "${CI:-}" = "true" ] || [ "${SB3_TD3X_START_SLURM:-}" = "1" ]; } && [ -f .ci/slurm.sh ]; then
  # shellcheck disable=SC1091
  . .ci/slurm.sh
fi

# The documentation must build with warnings as errors.
if [ -f mkdocs.yml ]; then
  mkdocs build --strict --quiet --site-dir site
fi

# Two processes for two cores; each test process uses one torch thread (tests/conftest.py).
python -m pytest -n 2 --dist loadfile --timeout 900 -q --durations=15 "$@"
