#!/usr/bin/env bash
# Shared installer for quickstart.sh and test.sh. Idempotent: every step checks before it acts.
# Usage: source pipelines/_install.sh   (sets VENV and activates it)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${FPP_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3}"

log() { printf '[install] %s\n' "$*" >&2; }

# 1. System libraries: OSMesa for off-screen GL, libGL + libXrender because pyrender imports pyglet.
need_apt=()
for pkg in libosmesa6 libgl1 libxrender1; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need_apt+=("$pkg")
done
# Debian's own python3 needs python3-venv for `python -m venv` (ensurepip); pyenv/conda builds have it.
if [ ! -x "$VENV/bin/python" ] && ! "$PY" -c 'import ensurepip, venv' 2>/dev/null; then
  need_apt+=("python3-venv")
fi
if [ ${#need_apt[@]} -gt 0 ]; then
  log "installing system packages: ${need_apt[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

# 2. Virtual environment.
if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtual environment $VENV"
  "$PY" -m venv "$VENV"
fi
# shellcheck disable=SC1091
source "$VENV/bin/activate"
pipq() { python -m pip install --disable-pip-version-check -q "$@"; }

# 3. torch pinned (an unpinned torch pulls several GB of CUDA wheels).
python -c 'import torch, sys; sys.exit(0 if torch.__version__.startswith("2.13.0") else 1)' 2>/dev/null \
  || { log "installing torch==2.13.0"; pipq torch==2.13.0; }

# 4. The package itself (editable) with test extras; re-run only when pyproject.toml changed.
stamp="$VENV/.fpp-installed"
if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ]; then
  log "installing the fppsim/uhrnet package and its dependencies"
  pipq -e "$ROOT[test]"
  touch "$stamp"
fi

# 5. An environment made before the switch to pyrender2 still has pyrender 0.1.45: both distributions
#    install the same `pyrender` package folder, so remove the old one and reinstall pyrender2's files.
if python -c 'import importlib.metadata as m; m.version("pyrender")' 2>/dev/null; then
  log "replacing pyrender 0.1.45 with pyrender2 (the maintained fork this package requires)"
  python -m pip uninstall --disable-pip-version-check -y -q pyrender
  pipq --force-reinstall --no-deps "pyrender2==0.2.2"
fi
export PYOPENGL_PLATFORM=osmesa
