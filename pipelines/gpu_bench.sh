#!/usr/bin/env bash
# GPU numbers for uhrnet, on an NVIDIA machine that has PyTorch but not our other dependencies.
# Usage: bash pipelines/gpu_bench.sh [OUTDIR]            (default out/gpu_bench; about 10-15 minutes on one GPU)
#   1. pip-installs what uhrnet needs besides torch (the torch already there is kept; no rendering libraries);
#      offline, uhrnet runs from this checkout with torch + numpy alone (the steps below need nothing else)
#   2. uhrnet bench: UHRNet and U-Net ms/image at batch 1 in fp32, bf16, fp16, fp16 + channels_last, compiled;
#      images/s over batch sizes for the fastest configuration
#   3. one AMP (fp16) training epoch of UHRNet on 1,500 synthetic random tensors at 352 x 640: time, finiteness
#   4. a world-size-1 nccl run of `torchrun -m uhrnet train` (2 epochs on a small generated figshare-layout set)
#   5. OUTDIR/gpu_bench.json collects everything (python pipelines/bench_report.py OUTDIR makes a page of it)
# Without CUDA the GPU steps are skipped. GPU_BENCH_TINY=1 shrinks everything (CPU dry run of the plumbing).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${1:-$ROOT/out/gpu_bench}"
PY="${PYTHON:-python}"
mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
log() { printf '[gpu_bench %s] %s\n' "$(date -u +%H:%M:%S)" "$*" | tee -a "$OUT/log.txt" >&2; }

"$PY" -c 'import torch' 2>/dev/null || { echo "gpu_bench: this needs a Python with PyTorch (set PYTHON=...)" >&2; exit 2; }
cd "$ROOT"

# 1. Dependencies: everything pyproject.toml lists except torch (keep the machine's CUDA build) and the
#    rendering stack (pyrender2, PyOpenGL: no fppsim rendering here), then this package without deps.
if ! "$PY" -c 'import uhrnet, scipy, skimage, yaml, tqdm, matplotlib' 2>/dev/null; then
  log "installing uhrnet's dependencies (torch kept as it is)"
  mapfile -t deps < <("$PY" - <<'PYEOF'
import re, tomllib
deps = tomllib.load(open("pyproject.toml", "rb"))["project"]["dependencies"]
print("\n".join(d for d in deps if re.split(r"[<>=!~ \[]", d)[0].lower() not in ("torch", "pyrender", "pyrender2")))
PYEOF
)
  if ! { "$PY" -m pip install -q "${deps[@]}" && "$PY" -m pip install -q --no-deps -e "$ROOT"; }; then
    # an offline machine: the steps below need only torch and numpy; uhrnet then runs from this checkout
    log "pip install failed (offline?): running uhrnet from $ROOT with what is installed (torch + numpy)"
    export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
  fi
fi
"$PY" -c 'import numpy, uhrnet' 2>/dev/null || { echo "gpu_bench: cannot import uhrnet here (it needs numpy besides torch)" >&2; exit 2; }
CUDA=$("$PY" -c 'import torch; print(int(torch.cuda.is_available()))')
TINY="${GPU_BENCH_TINY:-0}"
if [ "$CUDA" = 0 ] && [ "$TINY" = 0 ]; then
  log "no CUDA device: GPU steps skipped (GPU_BENCH_TINY=1 dry-runs them on the CPU)"
fi
T=$([ "$TINY" = 0 ] && echo 420 || echo 600)   # per-step limit (s), so the whole run stays under 15 minutes

log "step 2: uhrnet bench"
timeout "$T" "$PY" pipelines/gpu_bench.py bench "$OUT" >"$OUT/bench.log" 2>&1 || log "bench step failed (see $OUT/bench.log)"

log "step 3: one AMP training epoch"
timeout "$T" "$PY" pipelines/gpu_bench.py epoch "$OUT" >"$OUT/epoch.log" 2>&1 || log "epoch step failed (see $OUT/epoch.log)"

log "step 4: torchrun world size 1"
if [ "$CUDA" = 1 ] || [ "$TINY" != 0 ]; then
  DATA="$OUT/torchrun_data"; RUN="$OUT/torchrun_run"
  "$PY" pipelines/gpu_bench.py data "$DATA" >/dev/null
  rm -rf "$RUN"   # written by this script only
  SIZE=(); [ "$TINY" != 0 ] && SIZE=(--base-channels 4)
  AMP=(); [ "$CUDA" = 1 ] && AMP=(--amp)
  start=$(date +%s)
  if timeout "$T" "$PY" -m torch.distributed.run --standalone --nproc_per_node 1 -m uhrnet train --real "$DATA" \
      --model uhrnet "${SIZE[@]}" "${AMP[@]}" --epochs 2 --batch-size 2 --seed 0 --out "$RUN" --no-progress \
      >"$OUT/torchrun.log" 2>&1; then
    rc=0; else rc=$?; fi
  "$PY" - "$OUT" "$rc" "$(( $(date +%s) - start ))" "$CUDA" <<'PYEOF'
import sys
from pathlib import Path
from fppsim.files import json_text
from uhrnet.run_folder import LAST_PT
out, rc, secs, cuda = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
log = (out / "torchrun.log").read_text(errors="replace")
res = {"exit_code": rc, "seconds": secs, "backend": "nccl" if cuda else "gloo", "world_size": 1,
       "checkpoint_written": (out / "torchrun_run" / LAST_PT).is_file(), "log_tail": log.splitlines()[-5:]}
(out / "step_torchrun.json").write_text(json_text(res, indent=1) + "\n")
PYEOF
  [ "$rc" = 0 ] || log "torchrun step failed (exit $rc, see $OUT/torchrun.log)"
else
  log "torchrun step skipped: no CUDA device"
fi

"$PY" pipelines/gpu_bench.py collect "$OUT" >/dev/null
log "wrote $OUT/gpu_bench.json"
