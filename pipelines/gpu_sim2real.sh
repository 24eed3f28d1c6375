#!/usr/bin/env bash
# Sim-to-real at GPU scale, end to end on a fresh GPU machine: install what is missing, generate the
# synthetic data there (all CPU cores), train full UHRNet (352 x 640) on it alone, evaluate on the real
# pair(s), and keep only the small results (report, history, real-pair predictions and figures; NOT the
# 120 MB checkpoint).
#
#   bash pipelines/gpu_sim2real.sh [REAL_DIR ...]
#
# Assumes: a Linux machine with an NVIDIA GPU and a Python that already has PyTorch with CUDA; access to
# the Python package index (pip) and, only when libosmesa6/libgl1/libxrender1 are missing, to the apt
# package index. Nothing else is downloaded (no datasets, no weights). The real data must be uploaded
# with the repository (the published pair is 1.8 MB): REAL_DIR defaults to ../shared/real-sample, then
# shared/real-sample. Meshes: ../shared/meshes (or shared/meshes) when present, plus assets/meshes and
# the procedural sculptures that `fppsim generate` mixes in by default.
#
# Environment (all optional):
#   S2R_OUT      experiment folder            [runs/gpu_sim2real]
#   S2R_RESULTS  where the kept results go    [$OUT if set (device runner), else $S2R_OUT/results]
#   S2R_COUNT    synthetic samples            [the gpu scale's 2000]
#   S2R_EPOCHS   epochs                       [the gpu scale's value]
#   S2R_DEVICE   cuda or cpu                  [cuda]
#   S2R_ARGS     extra pipelines/sim2real.py arguments (e.g. "--base-channels 8" for a CPU dry run)
#   PYTHON       interpreter that has torch   [python3]
#   PYOPENGL_PLATFORM  osmesa or egl (the NVIDIA driver's EGL, e.g. on a machine without apt access) [osmesa]
# CPU dry run of the plumbing:  S2R_COUNT=8 S2R_EPOCHS=1 S2R_DEVICE=cpu S2R_ARGS="--base-channels 8" \
#                               bash pipelines/gpu_sim2real.sh
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
log() { printf '[gpu_sim2real %s] %s\n' "$(date -u +%H:%M:%S)" "$*" >&2; }
T0=$(date +%s)

# 1. System libraries for off-screen rendering (pyrender imports pyglet: libGL and libXrender too;
#    OSMesa only for the osmesa platform).
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"   # egl: GPU rendering where OSMesa is missing
pkgs=(libgl1 libxrender1); [ "$PYOPENGL_PLATFORM" = osmesa ] && pkgs+=(libosmesa6)
need=()
for pkg in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  log "apt: installing ${need[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi

# 2. Python packages: keep the machine's torch (a CUDA build); install our package without touching it.
"$PY" -c 'import torch' 2>/dev/null || { log "error: $PY has no torch; install a CUDA PyTorch first"; exit 1; }
if ! "$PY" -c 'import fppsim.cli, uhrnet.sim2real, pyrender, trimesh, skimage, cv2' 2>/dev/null; then
  log "pip: installing fppsim/uhrnet and its dependencies (torch kept)"
  pipq() { "$PY" -m pip install --disable-pip-version-check -q "$@"; }
  # every dependency from pyproject.toml except torch, then the package itself without dependencies
  deps=$("$PY" - <<'EOF'
import re
text = open("pyproject.toml").read()  # no tomllib before Python 3.11: read the dependencies array
block = re.search(r"^dependencies\s*=\s*\[(.*?)^\]", text, re.S | re.M).group(1)
deps = re.findall(r'"([^"]+)"', block)
print(" ".join(d for d in deps if not re.match(r"torch\b", d)))
EOF
)
  # shellcheck disable=SC2086
  pipq $deps
  pipq --no-deps -e .
fi
"$PY" -c 'import pyrender' >/dev/null 2>&1 || { log "error: pyrender does not import ($PYOPENGL_PLATFORM library missing?)"; exit 1; }

# 3. Inputs.
REAL=("$@")
if [ ${#REAL[@]} -eq 0 ]; then
  for d in ../shared/real-sample shared/real-sample; do [ -d "$d" ] && { REAL=("$d"); break; }; done
fi
[ ${#REAL[@]} -gt 0 ] || { log "error: no real data folder (give REAL_DIR or upload shared/real-sample)"; exit 2; }
MESHES=()
for d in ../shared/meshes shared/meshes; do [ -d "$d" ] && { MESHES+=("$d"); break; }; done
MESHES+=(assets/meshes)
S2R_OUT="${S2R_OUT:-runs/gpu_sim2real}"
RESULTS="${S2R_RESULTS:-${OUT:-$S2R_OUT/results}}"
args=(--scale gpu --real "${REAL[@]}" --meshes "${MESHES[@]}" --out "$S2R_OUT" --workers 0
      --device "${S2R_DEVICE:-cuda}")
[ -n "${S2R_COUNT:-}" ] && args+=(--count "$S2R_COUNT")
[ -n "${S2R_EPOCHS:-}" ] && args+=(--epochs "$S2R_EPOCHS")
# shellcheck disable=SC2206
[ -n "${S2R_ARGS:-}" ] && args+=(${S2R_ARGS})
log "nproc $(nproc); $("$PY" -c 'import torch; print("torch", torch.__version__, "cuda", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")')"

# 4. The experiment (resumable: a second call re-uses what the first finished).
set +e
"$PY" pipelines/sim2real.py "${args[@]}"
rc=$?
set -e

# 5. Keep the small results, whatever happened (no checkpoints, no datasets).
mkdir -p "$RESULTS"
for f in "$S2R_OUT"/report.json "$S2R_OUT"/report.md "$S2R_OUT"/data/*.log; do
  [ -f "$f" ] && cp "$f" "$RESULTS/"
done
for v in "$S2R_OUT"/*/; do
  name=$(basename "$v")
  [ "$name" = data ] || [ "$name" = results ] && continue
  mkdir -p "$RESULTS/$name"
  for f in "$v"run/history.csv "$v"run/history.png "$v"run/config.json "$v"train.log "$v"timing.json \
           "$v"eval/real_metrics.json "$v"eval/predictions.npz "$v"eval/*.png; do
    [ -f "$f" ] && cp "$f" "$RESULTS/$name/"
  done
done
log "exit $rc after $(( $(date +%s) - T0 )) s; results in $RESULTS"
exit $rc
