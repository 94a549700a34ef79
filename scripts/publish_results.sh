#!/usr/bin/env bash
# Publishes the runs made by scripts/results.sh to the docs: copies each run's small records (evaluations.csv,
# config.yaml, summary.json, provenance.jsonl; no checkpoints) to docs/assets/results/runs/, then aggregates them
# into the tables and plots that docs/results.md shows. The finished seeds of a group (those with a summary.json) are
# aggregated; a group with no finished seed yet is aggregated as far as all its seeds have got.
#
#   bash scripts/publish_results.sh [RUNS_DIR]     # default runs/results
#
# Then scripts/results_tables.py rewrites the tables of docs/results.md (RESULTS_PAGE; empty: leave the page alone).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
src=$(realpath -m "${1:-$root/runs/results}")  # paths given by the caller are relative to the caller's folder
dst=$(realpath -m "${RESULTS_DOCS_DIR:-$root/docs/assets/results}")
cd "$root"
# The project's venv where there is one and PYTHON does not name an interpreter (as scripts/test.sh does).
[ -z "${PYTHON:-}" ] && [ -f .venv/bin/activate ] && . .venv/bin/activate
python=${PYTHON:-python}
[[ -d $src ]] || { echo "error: no folder $src; make the runs first with scripts/results.sh" >&2; exit 2; }

records=()
while IFS= read -r -d '' file; do records+=("$file"); done < <(find "$src" -path '*/checkpoints' -prune -o \
  -path '*/.hydra' -prune -o -type f \
  \( -name evaluations.csv -o -name config.yaml -o -name summary.json -o -name provenance.jsonl \) -print0)

# Nothing is published while one record holds something that looks like a secret (a URL's password, an API key):
# the check names the file and line, with the secret masked.
# Status 3 is a finding; any other failure is the check's own (a Python without this package, say), said as such.
if ((${#records[@]})); then
  status=0
  "$python" -m sb3_td3x.common.redaction "${records[@]}" || status=$?
  if ((status == 3)); then
    echo "error: not publishing: the records above look like they hold a secret; mask it (e.g. ***) in those files" \
      "or leave them out, then run this again" >&2
    exit 2
  elif ((status != 0)); then
    echo "error: not publishing: the secret check ($python -m sb3_td3x.common.redaction) failed with status" \
      "$status (above); set PYTHON to the interpreter this package is installed in, then run this again" >&2
    exit 2
  fi
fi

# A published run is never replaced by a shorter one: runs made here with fewer steps (a 100k-step table in the same
# runs/results/<env>/<algo>/seed<k> folders as the published 200k ones, say) would overwrite its records.
status=0
shorter=$("$python" scripts/results_tables.py --docs-dir "$dst" --shorter-runs "$src") || status=$?
if ((status == 3)); then
  shorter=${shorter//$'\n'/; }
  echo "error: not publishing: it would replace published runs with shorter ones: ${shorter:0:600}." \
    "Publish runs of another length from a folder of their own with RESULTS_DOCS_DIR set elsewhere, or finish these" \
    "runs first" >&2
  exit 2
elif ((status != 0)); then
  echo "error: not publishing: the check for shorter runs (scripts/results_tables.py --shorter-runs) failed with" \
    "status $status (above)" >&2
  exit 2
fi

for file in "${records[@]}"; do
  relative=${file#"$src"/}
  mkdir -p "$dst/runs/$(dirname "$relative")"
  cp "$file" "$dst/runs/$relative"
done

aggregate() {  # OUT_NAME then group folders <env>/<algo> (those that exist)
  local out=$1 dirs=() group seed finished
  shift
  for group in "$@"; do
    [[ -d $group ]] || continue
    finished=()
    for seed in "$group"/seed*/; do [[ -f $seed/summary.json ]] && finished+=("${seed%/}"); done
    if ((${#finished[@]})); then dirs+=("${finished[@]}"); else dirs+=("$group"); fi
  done
  if ((${#dirs[@]})); then
    echo "== $out"
    "$python" -m sb3_td3x.experiment.analysis.aggregate "${dirs[@]}" --out "$dst/$out"
    rm -f "$dst/$out/aggregate.md"  # printed above and kept as aggregate.csv; a .md under docs/ would be a page
  fi
}
# The groups are defined once, in scripts/results_tables.py (GROUPS): one line each, its name then its folders.
groups=$("$python" scripts/results_tables.py --groups)
while read -r name folders; do
  read -r -a folders <<<"$folders"
  # A group published from runs whose records are not here is left alone: aggregating it again would drop them.
  if ! missing=$("$python" scripts/results_tables.py --docs-dir "$dst" --missing-runs "$name"); then
    echo "== $name: left as published; its runs' records are not under $dst/runs: $(echo $missing | head -c 300)" >&2
    continue
  fi
  aggregate "$name" "${folders[@]/#/$dst/runs/}"
done <<<"$groups"

page=${RESULTS_PAGE-$root/docs/results.md}
if [[ -n $page ]]; then
  "$python" scripts/results_tables.py --docs-dir "$dst" --page "$page"
fi
