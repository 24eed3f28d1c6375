#!/usr/bin/env bash
# The scaling study as a background job across sessions (issue 35; docs/experiments/scaling.md).
#
#   bash pipelines/scaling_job.sh n100:0 n100:1 n400:0 ...      # (arm, seed)s, in this order
#
# Runs each (arm, seed) at full size on the CPU under `nice`, from a git worktree of the current HEAD
# (WORKTREE, default ../study-<short commit>) so that later edits of this checkout never change a running seed
# and every seed records the commit it ran. After each seed its result is merged into this checkout's
# docs/experiments/scaling.json (scaling.py --ledger: nothing recorded is ever dropped), the table and the
# figures are rewritten, and those files alone are committed. A seed cut off resumes when the same (arm, seed)
# is asked for again from the same worktree; a new session (new worktree) restarts it cleanly.
# Log: WORKTREE/runs/scaling/job.log. Environment: WORKTREE, PY (default .venv/bin/python of this checkout).
# Exit status: 0 every seed done, 1 a seed failed (the others still ran), 2 bad arguments (nothing created).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
[ $# -gt 0 ] || { echo "usage: scaling_job.sh ARM:SEED [ARM:SEED ...]" >&2; exit 2; }
for item in "$@"; do
  [[ "$item" =~ ^[A-Za-z0-9._-]+:[0-9]+$ ]] || { echo "scaling_job.sh: error: '$item' is not ARM:SEED" >&2; exit 2; }
done
PY="${PY:-$ROOT/.venv/bin/python}"
[ -x "$PY" ] || { echo "scaling_job.sh: error: no python at $PY (run bash pipelines/test.sh once, or set PY)" >&2; exit 2; }
# the arms and seeds are checked by scaling.py itself before anything is created (no worktree for a bad arm)
arms=() seeds=()
for item in "$@"; do arms+=("${item%%:*}"); seeds+=("${item##*:}"); done
uniq_arms=($(printf '%s\n' "${arms[@]}" | awk '!seen[$0]++'))
uniq_seeds=($(printf '%s\n' "${seeds[@]}" | awk '!seen[$0]++'))
(cd "$ROOT" && "$PY" pipelines/scaling.py --list --arms "${uniq_arms[@]}" --seeds "${uniq_seeds[@]}" \
   --real ../shared/real-sample --real-phase none --meshes assets/meshes >/dev/null) \
  || { echo "scaling_job.sh: error: refused by scaling.py (above); nothing created" >&2; exit 2; }
commit="$(git -C "$ROOT" rev-parse HEAD)"
WT="${WORKTREE:-$(dirname "$ROOT")/study-${commit:0:10}}"
if [ ! -d "$WT" ]; then
  git -C "$ROOT" worktree add --detach "$WT" "$commit" >/dev/null
fi
LEDGER="$ROOT/docs/experiments/scaling.json"
mkdir -p "$WT/runs/scaling"
cd "$WT"
export PYTHONPATH="$WT${PYTHONPATH:+:$PYTHONPATH}" PYOPENGL_PLATFORM=osmesa
run_all() {
failed=0
for item in "$@"; do
  arm="${item%%:*}" seed="${item##*:}"
  echo "$(date -Is) start $arm seed $seed at $(git rev-parse --short HEAD)"
  if nice -n 10 "$PY" pipelines/scaling.py --arms "$arm" --seeds "$seed" --out runs/scaling --ledger "$LEDGER" \
      --real ../shared/real-sample --real-phase ../shared/real-phase/FP1523 \
      --meshes ../shared/meshes assets/meshes; then
    git -C "$ROOT" add -- docs/experiments/scaling.json docs/experiments/scaling_table.md "docs/experiments/scaling_*.png" || true
    git -C "$ROOT" commit -q -m "scaling study: $arm seed $seed (full size, CPU, code at $(git rev-parse --short HEAD))" \
      -- docs/experiments/scaling.json docs/experiments/scaling_table.md docs/experiments/scaling_*.png \
      && echo "$(date -Is) committed $arm seed $seed"
  else
    failed=1
    logs=$(ls "$WT/runs/scaling/$arm/s$seed/"*.log "$WT/runs/scaling/$arm/data/"*.log 2>/dev/null | tr '\n' ' ' || true)
    echo "$(date -Is) $arm seed $seed failed (its output is above, in $WT/runs/scaling/job.log${logs:+; stage logs: $logs})"
  fi
done
return "$failed"
}
# exit 1 when a seed failed (its status comes through the pipe: set -o pipefail, set -e)
run_all "$@" 2>&1 | tee -a "$WT/runs/scaling/job.log"
