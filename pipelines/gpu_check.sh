#!/usr/bin/env bash
# The GPU check: everything this project wants measured on a GPU, in one offline run that fits the
# ~15 minutes a GPU machine is lent (starts included). It needs no network on the GPU machine: what its
# image lacks (trimesh, pyrender2, PyOpenGL, pyglet, freetype-py, zlib-ng; the GL loader libraries for
# EGL) travels with the checkout, fetched beforehand by `prepare` on a machine that has a network.
#
#   bash pipelines/gpu_check.sh prepare          networked machine, once: wheels -> .whl/, EGL/X11 loader
#                                                debs -> .gl/, ../shared real data -> .gpu_data/ (all git-ignored)
#   bash pipelines/gpu_check.sh [run] [OUTDIR]   GPU machine, offline   [OUTDIR: out/gpu_check]
#
# Steps (each under its own time limit, cut to what the budget has left; a failed step is reported, the
# others still run):
#   s. training speed before / after the speed options (issue 49): UHRNet samples/s at 352 x 640, seconds of
#      one study seed (the recipe's U-Net), each step's share in data / forward / backward / optimizer
#                                                                   (pipelines/gpu_speed.py; OUTDIR/speed.json,
#      also docs/benchmarks/gpu/<date>_<card>.json in the checkout: commit OUTDIR/speed.json under that name)
#   0. the scaling study's arms at full size on the GPU, several at once (issue 35: it comes first in the
#      budget): pipelines/scaling.py --device cuda --jobs N --deadline S, seeds 0 1 2, scored on the real pair
#      and FP1523 in .gpu_data/; OUTDIR/study.json is its study record (merge it into the study's with
#      `python pipelines/scaling.py --ledger docs/experiments/scaling.json --merge study.json`)
#   1. forward ms per 352 x 640 image, batch 1, UHRNet / U-Net / hNet (the paper's Table 3 column), fp32
#      and fp16 + channels_last                                     (uhrnet bench)
#   2. synthetic data generated there, rendered through EGL (all cores; samples/s)   (fppsim generate)
#   3. a short training run of UHRNet on it, AMP on a GPU (training samples/s of whole epochs, validation
#      included)                                                                    (uhrnet train --amp)
#   4. one DistributedDataParallel epoch on nccl, world size 1        (torchrun -m uhrnet train)
#   5. one point of the sim-to-real curve at GPU scale: step 3's model scored on the real pair and real
#      phase frames in .gpu_data/                                      (uhrnet sim2real --reuse-run)
# OUTDIR/gpu_check.json and OUTDIR/gpu_check.md hold the numbers, OUTDIR/*.log each step's output
# (a handful of small files; no checkpoints or datasets: those stay in OUTDIR/work). OUTDIR must be new, empty
# or an earlier run's (its .gpu_check marker); a re-run replaces only what this script wrote there (the
# record OUTDIR/.fppsim-owned.json) and refuses, in one line naming it, a path it has to write that is not its own.
# A relative OUTDIR is taken from the folder the script was started in. Ctrl-C (or SIGTERM) stops the running
# step and the run (exit 130; 143); the steps also die with the script when it is killed with -9, and a re-run
# then removes only what the stopped run wrote (gpu_check.py's docstring).
#
# Environment (optional):
#   GPU_CHECK_BUDGET  seconds the whole run may take, 60 to 86400   [600: 10 minutes + a machine start fits in 15]
#                     (sizes: >= 600 s: 2000 samples, 3 epochs; >= 400 s: 1200, 2; less: 800, 2)
#   GPU_CHECK_TINY=1  dry run of the plumbing on a CPU at tiny sizes (what CI-like machines can check)
#   GPU_CHECK_STEPS   the steps to run, in the order above   [speed study forward generate train ddp sim2real]
#   GPU_CHECK_STUDY   the study's arms (pipelines/scaling_arms.yaml), run at once   [n100 n400 n1600 n6400 pedestal-0.8]
#   GPU_CHECK_STUDY_SEEDS  the training seeds of each study arm (a study's pending ones)   [0 1 2]
#   GPU_CHECK_SPEED_ARGS  the speed step's 'after' also with: --compile (torch.compile), --recipe-amp (the recipe
#                     seed with --amp too)   [none]
#   GPU_CHECK_STUDY_SHARE  percent of the budget the study may take when other steps follow   [60]
#   STUDY_COMMIT      the commit of the checkout sent (a copy without git), recorded with every study seed
#   PYTHON            the interpreter that holds PyTorch                 [python3]
# On the lent machine (the device tool): carry .whl .gl .gpu_data and run
#   bash pipelines/gpu_check.sh run "$OUT"
# Offline dry run on a CPU: docs/USAGE.md ("GPU, offline").
set -euo pipefail
CALLER_PWD="$PWD"   # a relative OUTDIR is the caller's, not the checkout's
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
MODE="${1:-run}"
case "$MODE" in
  prepare|run) shift || true ;;
  -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
  *) MODE=run ;;  # bash gpu_check.sh OUTDIR
esac
log() { printf '[gpu_check %s] %s\n' "$(date -u +%H:%M:%S)" "$*" >&2; }

# The packages the GPU image lacks, at the versions this project is tested with.
WHEELS=(trimesh==5.2.0 pyrender2==0.2.2 PyOpenGL==3.1.10 pyglet==2.1.19 freetype-py==2.5.1 zlib-ng==1.1.0)
GL_DEBS=(libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)          # unpacked over / (glvnd loaders only)
X11_DEBS=(libxrender1 libx11-6 libxcb1 libxau6 libxdmcp6 libxext6 libbsd0 libmd0)  # pyglet's, beside / if missing

if [ "$MODE" = prepare ]; then
  mkdir -p .whl .gl/x11
  plat=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
        --platform manylinux2014_x86_64 --platform manylinux_2_12_x86_64 --platform manylinux2010_x86_64
        --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64)
  # the GPU image's Python (3.12) and this machine's (for the CPU dry run)
  for v in 3.12 "$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"; do
    log "wheels for Python $v -> .whl/"
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$v" --implementation cp \
      "${plat[@]}" -d .whl "${WHEELS[@]}"
  done
  if command -v apt-get >/dev/null; then
    o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/gpu_check_apt)
    mkdir -p /tmp/gpu_check_apt/partial
    log "EGL and X11 loader packages -> .gl/"
    apt-get "${o[@]}" update -qq
    (cd .gl && apt-get "${o[@]}" download "${GL_DEBS[@]}" 2>/dev/null)
    (cd .gl/x11 && apt-get "${o[@]}" download "${X11_DEBS[@]}" 2>/dev/null)
  else
    log "no apt-get here: .gl/ not filled (the GPU machine must then have libEGL/libOpenGL already)"
  fi
  mkdir -p .gpu_data
  for d in real-sample real-phase meshes; do
    src="../shared/$d"
    [ -d "$src" ] || continue
    rm -rf ".gpu_data/$d"   # .gpu_data is this script's own copy
    cp -r "$src" ".gpu_data/$d"
  done
  log "ready: carry .whl .gl .gpu_data ($(du -sh .whl .gl .gpu_data 2>/dev/null | awk '{print $1}' | paste -sd+ -) ); then: bash pipelines/gpu_check.sh run OUTDIR"
  exit 0
fi

TINY="${GPU_CHECK_TINY:-0}"
BUDGET="${GPU_CHECK_BUDGET:-600}"
# digits only and a bounded length before any arithmetic (bash's own errors otherwise; 0600 is not octal)
[[ "$BUDGET" =~ ^[0-9]{1,9}$ ]] && BUDGET=$(( 10#$BUDGET )) && [ "$BUDGET" -ge 60 ] && [ "$BUDGET" -le 86400 ] \
  || { echo "gpu_check: GPU_CHECK_BUDGET must be a whole number of seconds from 60 to 86400, got '${GPU_CHECK_BUDGET}'" >&2; exit 2; }
[[ "$TINY" =~ ^[01]$ ]] || { echo "gpu_check: GPU_CHECK_TINY must be 0 or 1, got '$TINY'" >&2; exit 2; }
ALL_STEPS="speed study forward generate train ddp sim2real"
read -r -a STEPS <<< "${GPU_CHECK_STEPS:-$ALL_STEPS}"
for s in "${STEPS[@]}"; do
  [[ " $ALL_STEPS " == *" $s "* ]] || { echo "gpu_check: GPU_CHECK_STEPS: unknown step '$s' (steps: $ALL_STEPS)" >&2; exit 2; }
done
[ ${#STEPS[@]} -gt 0 ] || { echo "gpu_check: GPU_CHECK_STEPS names no step (steps: $ALL_STEPS)" >&2; exit 2; }
want() { [[ " ${STEPS[*]} " == *" $1 "* ]]; }
read -r -a STUDY_ARMS <<< "${GPU_CHECK_STUDY-n100 n400 n1600 n6400 pedestal-0.8}"
if want study && [ ${#STUDY_ARMS[@]} -eq 0 ]; then
  echo "gpu_check: GPU_CHECK_STUDY names no arm (leave study out of GPU_CHECK_STEPS to skip it)" >&2; exit 2
fi
for a in "${STUDY_ARMS[@]}"; do
  [[ "$a" =~ ^[A-Za-z0-9._-]{1,64}$ ]] || { echo "gpu_check: GPU_CHECK_STUDY: '$a' is not an arm name" >&2; exit 2; }
done
read -r -a STUDY_SEEDS <<< "${GPU_CHECK_STUDY_SEEDS-0 1 2}"
if want study && [ ${#STUDY_SEEDS[@]} -eq 0 ]; then
  echo "gpu_check: GPU_CHECK_STUDY_SEEDS names no seed" >&2; exit 2
fi
for x in "${STUDY_SEEDS[@]}"; do
  [[ "$x" =~ ^[0-9]{1,9}$ ]] || { echo "gpu_check: GPU_CHECK_STUDY_SEEDS: '$x' is not a seed (a whole number)" >&2; exit 2; }
done
read -r -a SPEED_EXTRA <<< "${GPU_CHECK_SPEED_ARGS-}"
for a in "${SPEED_EXTRA[@]}"; do
  case "$a" in --compile|--recipe-amp) ;; *) echo "gpu_check: GPU_CHECK_SPEED_ARGS: '$a' (known: --compile --recipe-amp)" >&2; exit 2 ;; esac
done
SHARE="${GPU_CHECK_STUDY_SHARE:-60}"
[[ "$SHARE" =~ ^[0-9]{1,3}$ ]] && [ "$((10#$SHARE))" -ge 10 ] && [ "$((10#$SHARE))" -le 100 ] \
  || { echo "gpu_check: GPU_CHECK_STUDY_SHARE must be a percent from 10 to 100, got '$SHARE'" >&2; exit 2; }
SHARE=$((10#$SHARE))
if [ -n "${STUDY_COMMIT+x}" ] && ! [[ "$STUDY_COMMIT" =~ ^[0-9a-f]{40}$ ]]; then
  echo "gpu_check: STUDY_COMMIT must be the full commit (40 lowercase hex digits), got '$STUDY_COMMIT'" >&2; exit 2
fi
others=0; for s in "${STEPS[@]}"; do [ "$s" != study ] && others=1; done
# the steps after the study are sized by, and share, what the study leaves of the budget
REST=$BUDGET; want study && REST=$(( BUDGET * (100 - SHARE) / 100 ))
OUTDIR="${1:-$ROOT/out/gpu_check}"
case "$OUTDIR" in /*) ;; *) OUTDIR="$CALLER_PWD/$OUTDIR" ;; esac
# OUTDIR is this script's own: new, empty, or an earlier run's (its .gpu_check marker); never someone's folder
if { [ -e "$OUTDIR" ] || [ -L "$OUTDIR" ]; } && [ ! -d "$OUTDIR" ]; then
  echo "gpu_check: $OUTDIR exists and is not a folder: give a new or empty OUTDIR" >&2; exit 2
fi
if [ -d "$OUTDIR" ] && [ -n "$(ls -A "$OUTDIR")" ] && [ ! -f "$OUTDIR/.gpu_check" ]; then
  echo "gpu_check: $OUTDIR holds files this script did not write: give a new or empty OUTDIR" >&2; exit 2
fi
"$PY" -c 'import torch, numpy' 2>/dev/null || { echo "gpu_check: $PY has no PyTorch (set PYTHON=...)" >&2; exit 2; }
# the sizes, and the refusal of a GPU run without a GPU, before anything is written
CUDA=$("$PY" -c 'import torch; print(int(torch.cuda.is_available()))')
NPROC=$(nproc)
if [ "$TINY" != 0 ]; then
  H=64; W=128; COUNT=8; EPOCHS=1; BATCH=2; WIDTH=(--base-channels 4); DEV=cpu; REPEATS=(--repeats 1 --warmup 1)
  GENW=2; AMP=(); [ "$CUDA" = 1 ] && { DEV=cuda; AMP=(--amp); }   # bf16 autocast on a CPU is slow
elif [ "$REST" -ge 600 ]; then
  H=352; W=640; COUNT=2000; EPOCHS=3; BATCH=8; WIDTH=(); DEV=cuda; REPEATS=(--repeats 30 --warmup 10)
  GENW=$NPROC; AMP=(--amp)
else
  H=352; W=640; COUNT=$([ "$REST" -ge 400 ] && echo 1200 || echo 800); EPOCHS=2; BATCH=8; WIDTH=(); DEV=cuda
  REPEATS=(--repeats 20 --warmup 5); GENW=$NPROC; AMP=(--amp)
fi
[ "$DEV" = cuda ] && [ "$CUDA" = 0 ] && { echo "gpu_check: no CUDA device here (GPU_CHECK_TINY=1 dry-runs on the CPU)" >&2; exit 2; }
# an earlier run's own files go (a killed run leaves no stale step for the report), nothing else; this run's
# names are claimed (OUTDIR/.fppsim-owned.json) before they are written; one line and exit 2 if OUTDIR cannot be used
"$PY" pipelines/gpu_check.py begin "$OUTDIR" || exit 2
OUTDIR="$(cd "$OUTDIR" && pwd)"
trap '"$PY" pipelines/gpu_check.py settle "$OUTDIR" || true' EXIT   # record what the run wrote under work/
STEP_PID=
# a signal stops the running step (its guard signals the step's process group, SIGKILL 10 s later), then the
# run: settled by the EXIT trap, exit 128 + N
stop() {
  trap '' INT TERM HUP
  if [ -n "$STEP_PID" ]; then kill -s "$1" "$STEP_PID" 2>/dev/null || true; wait "$STEP_PID" 2>/dev/null || true; fi
  log "stopped (SIG$1)"
  exit "$2"
}
trap 'stop INT 130' INT
trap 'stop TERM 143' TERM
trap 'stop HUP 129' HUP
WORK="$OUTDIR/work"
T0=$(date +%s)
left() { echo $(( BUDGET - ($(date +%s) - T0) )); }
# a step may take CAP seconds, but never what the later steps need (RESERVE: a share of the budget)
limit() { local cap=$1 reserve=$2 l; l=$(( $(left) - reserve )); [ "$l" -lt "$cap" ] && cap=$l; echo $(( cap < 5 ? 5 : cap )); }
# guarded LOG LIMIT CMD...: CMD into LOG, through gpu_check.py's guard: in its own process group, at most LIMIT
# seconds (exit 124, like timeout), stopped with the script (Ctrl-C, kill, even kill -9 of this shell), the run
# marked alive meanwhile. Waited for in the background, so that a signal is handled at once.
guarded() {
  local logf=$1 lim=$2 rc=0; shift 2
  "$PY" pipelines/gpu_check.py guard "$OUTDIR" "$lim" "$@" >"$logf" 2>&1 &
  STEP_PID=$!
  wait "$STEP_PID" || rc=$?
  STEP_PID=
  return "$rc"
}

# 0. The environment: carried wheels into a private site folder (never pip's network), GL loaders.
SITE="$WORK/site"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
# (not when the interpreter has them already: a pip install here is minutes of CPU for nothing)
if compgen -G ".whl/*.whl" >/dev/null && ! "$PY" -c 'import trimesh, pyrender, OpenGL, pyglet, freetype' 2>/dev/null; then
  mapfile -t whl < <("$PY" pipelines/gpu_check.py wheels .whl)
  if [ ${#whl[@]} -gt 0 ]; then
    log "installing ${#whl[@]} carried wheels into $SITE (no index, no network)"
    guarded "$OUTDIR/setup.log" "$(limit 600 0)" "$PY" -m pip install -q --no-index --no-deps --no-compile \
      --no-cache-dir --disable-pip-version-check --target "$SITE" "${whl[@]}" || log "wheel install failed (see setup.log)"
    export PYTHONPATH="$PYTHONPATH:$SITE"   # after the image's own packages: theirs win where both exist
  fi
fi
if [ "$CUDA" = 1 ]; then
  export PYOPENGL_PLATFORM=egl
  if [ "$(id -u)" = 0 ] && compgen -G ".gl/*.deb" >/dev/null && ! ldconfig -p | grep -q 'libEGL.so.1 '; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done   # the README's recipe: glvnd loaders only
    ldconfig
  fi
  nv=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [ -f "$nv" ] && export __EGL_VENDOR_LIBRARY_FILENAMES="${__EGL_VENDOR_LIBRARY_FILENAMES:-$nv}"
else
  # the CPU dry run renders through OSMesa where it exists, else Mesa's EGL
  if ldconfig -p 2>/dev/null | grep -q libOSMesa; then export PYOPENGL_PLATFORM=osmesa; else export PYOPENGL_PLATFORM=egl; fi
fi
if ! ldconfig -p 2>/dev/null | grep -q 'libXrender.so.1 ' && compgen -G ".gl/x11/*.deb" >/dev/null; then
  # pyglet (imported by pyrender) loads libX11/libXrender even headless; unpacked beside /, not over it
  for f in .gl/x11/*.deb; do dpkg -x "$f" "$WORK/x11"; done
  touch "$OUTDIR/.gpu_check"   # the run alive after writing work/x11 (gpu_check.py heartbeat)
  export LD_LIBRARY_PATH="$WORK/x11/usr/lib/x86_64-linux-gnu${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
"$PY" pipelines/gpu_check.py env "$OUTDIR" "$BUDGET" "$TINY" "$PYOPENGL_PLATFORM" >/dev/null

# run_step NAME LIMIT CMD...: time a command into OUTDIR/NAME.log and OUTDIR/step_NAME.json
run_step() {
  local name=$1 lim=$2 start rc; shift 2
  log "step $name (limit ${lim} s): $*"
  start=$(date +%s.%N)
  rc=0; guarded "$OUTDIR/$name.log" "$lim" "$@" || rc=$?
  "$PY" pipelines/gpu_check.py step "$OUTDIR" "$name" "$rc" "$start" "$lim" >/dev/null
  [ "$rc" = 0 ] || log "step $name failed (exit $rc; see $name.log)"
  return 0
}

MESHES=(assets/meshes); [ -d .gpu_data/meshes ] && MESHES+=(.gpu_data/meshes)
REAL=(); [ -d .gpu_data/real-sample ] && REAL=(.gpu_data/real-sample)
PHASE=(); for d in .gpu_data/real-phase/*/; do [ -d "$d/PSin" ] && PHASE+=("${d%/}"); done

# s. Training speed before / after the speed options (issue 49), in one process: the numbers the issue judges
if want speed; then
  SPEED=(--out "$WORK/speed" --bench-dir "$ROOT/docs/benchmarks/gpu")
  [ "$TINY" != 0 ] && SPEED=(--out "$WORK/speed" --tiny --bench-dir "$WORK/speed/bench")   # a dry run leaves docs/ alone
  run_step speed "$(limit 420 $(( BUDGET * 30 / 100 )))" "$PY" pipelines/gpu_speed.py "${SPEED[@]}" "${SPEED_EXTRA[@]}"
  [ -f "$WORK/speed/speed.json" ] && cp "$WORK/speed/speed.json" "$OUTDIR/speed.json"
fi

# 0. The scaling study first: its arms at once, each arm's seeds in turn, stopped at a deadline inside the step's
#    limit so that what finished is recorded (OUTDIR/study.json); scored as on the CPU (the pair, FP1523), the
#    meshes in the CPU study's order (../shared/meshes, then assets/meshes)
if want study; then
  if [ ${#REAL[@]} -eq 0 ]; then
    log "step study skipped: no .gpu_data/real-sample (run prepare)"
  else
    SARMS=(--arms "${STUDY_ARMS[@]}"); SMESH=(assets/meshes); [ -d .gpu_data/meshes ] && SMESH=(.gpu_data/meshes assets/meshes)
    SPHASE=(none); [ -d .gpu_data/real-phase/FP1523/PSin ] && SPHASE=(.gpu_data/real-phase/FP1523)
    if [ "$TINY" != 0 ]; then   # the plumbing at toy sizes: two tiny arms of the study's shape
      mkdir -p "$WORK/study"
      printf '%s\n' "defaults: {base_channels: 4, epochs: 1, batch_size: 2, workers: 1, loss: l2}" "arms:" \
        "  - {name: t6, series: [samples], count: 6, train: --samples-per-epoch 4}" \
        "  - {name: t8, series: [samples], count: 8, train: --samples-per-epoch 4}" > "$WORK/study/arms.yaml"
      SARMS=(--arms-file "$WORK/study/arms.yaml" --arms t6 t8 --resize 32x64); SPHASE=(none)
    fi
    slim=$(limit 86400 $(( others ? REST : 5 )))
    run_step study "$slim" "$PY" pipelines/scaling.py "${SARMS[@]}" --seeds "${STUDY_SEEDS[@]}" --out "$WORK/study" \
      --ledger "$OUTDIR/study.json" --real "${REAL[@]}" --real-phase "${SPHASE[@]}" --meshes "${SMESH[@]}" \
      --device "$DEV" --workers "$([ "$TINY" != 0 ] && echo 1 || echo 3)" --jobs "${#STUDY_ARMS[@]}" \
      --deadline "$(( slim > 120 ? slim - 60 : slim / 2 ))" --no-figures
  fi
  # the later steps' limits and reserves are shares of what is left now, not of the whole budget
  BUDGET=$(( $(left) > 60 ? $(left) : 60 )); T0=$(date +%s)
fi

# 1. Table 3's speed column
want forward && run_step forward_fp32 "$(limit 90 $(( BUDGET * 70 / 100 )))" "$PY" -m uhrnet bench --models uhrnet unet hnet --no-train --device "$DEV" \
  --height "$H" --width "$W" "${REPEATS[@]}" "${WIDTH[@]}" --json "$OUTDIR/forward_fp32.json"
if want forward && [ "$DEV" = cuda ]; then
  run_step forward_fp16 "$(limit 60 $(( BUDGET * 62 / 100 )))" "$PY" -m uhrnet bench --models uhrnet unet hnet --no-train --device cuda \
    --height "$H" --width "$W" "${REPEATS[@]}" --amp fp16 --channels-last --json "$OUTDIR/forward_fp16.json"
fi
# 2. data generated there, through EGL on the GPU (the recipe's generator settings, figshare layout)
want generate && run_step generate "$(limit 150 $(( BUDGET * 45 / 100 )))" "$PY" -m fppsim generate --meshes "${MESHES[@]}" --out "$WORK/syn" \
  --count "$COUNT" --seed 100 --workers "$GENW" --no-psp --format figshare --backend "$PYOPENGL_PLATFORM" --no-preview
# 3. UHRNet (AMP on a GPU) on that data (the sim-to-real gpu scale's loss, batch and lr); 5 reuses the run
TRAIN=(--synthetic "$WORK/syn" --model uhrnet "${WIDTH[@]}" --loss compound --epochs "$EPOCHS" --batch-size "$BATCH"
       --lr 3e-4 --seed 0 "${AMP[@]}" --device "$DEV" --no-progress)
want train && run_step train "$(limit 330 $(( BUDGET * 15 / 100 )))" "$PY" -m uhrnet train "${TRAIN[@]}" --out "$WORK/run"
# 4. DDP on nccl (gloo without CUDA), world size 1, one short epoch (gloo on the loopback: the dry run's
#    network namespace has no other interface)
export GLOO_SOCKET_IFNAME="${GLOO_SOCKET_IFNAME:-lo}"
want ddp && run_step ddp "$(limit "$([ "$TINY" != 0 ] && echo 240 || echo 90)" $(( BUDGET * 8 / 100 )))" "$PY" -m torch.distributed.run --standalone --nproc_per_node 1 -m uhrnet train \
  --synthetic "$WORK/syn" --model uhrnet "${WIDTH[@]}" --epochs 1 --samples-per-epoch $(( 4 * BATCH )) \
  --batch-size "$BATCH" "${AMP[@]}" --seed 0 --no-progress --out "$WORK/ddp"
# 5. the sim-to-real point: step 3's run scored on the real data that travelled
if ! want sim2real; then
  :
elif [ ${#REAL[@]} -gt 0 ] && [ -f "$WORK/run/last.pt" ]; then
  S2R=(--scale "$([ "$DEV" = cuda ] && echo gpu || echo cpu)" --real "${REAL[@]}" --out "$WORK/s2r" --count "$COUNT" --seed 100 --epochs "$EPOCHS"
       --batch-size "$BATCH" --lr 3e-4 --model uhrnet --device "$DEV" --reuse-run "default=$WORK/run" --no-figures)
  [ ${#PHASE[@]} -gt 0 ] && S2R+=(--real-phase "${PHASE[@]}")
  [ "$TINY" != 0 ] && S2R+=(--base-channels 4)
  run_step sim2real "$(limit 120 3)" "$PY" -m uhrnet sim2real "${S2R[@]}"
else
  log "step sim2real skipped: $([ ${#REAL[@]} -eq 0 ] && echo 'no .gpu_data/real-sample (run prepare)' || echo 'no trained run')"
fi
"$PY" pipelines/gpu_check.py report "$OUTDIR" >/dev/null
log "done in $(( $(date +%s) - T0 )) s of a ${BUDGET} s budget: $OUTDIR/gpu_check.md"
cat "$OUTDIR/gpu_check.md"
if [ -f "$OUTDIR/study_table.md" ]; then echo; cat "$OUTDIR/study_table.md"; fi
