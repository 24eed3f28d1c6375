#!/usr/bin/env bash
# Quickstart: install everything (idempotent), then the whole story on the embedded defaults:
#   1. generate a small synthetic dataset from the meshes in assets/meshes (+ preview PNG)
#   2. train a tiny UHRNet for a few minutes on CPU (synthetic + real figshare data when available)
#   3. evaluate it like the paper (Table 3 + figures) and predict one image (height map + point cloud)
# Usage: bash pipelines/quickstart.sh [--real DIR] [--out DIR] [--count N] [--epochs N]
#   --real DIR   a figshare-format folder (f1_80.npy + Z.npy, or fringe_pattern.npy + height_map.npy);
#                default: ../shared/real-sample when present
# Re-running resumes: finished samples and epochs are kept.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="$ROOT/out/quickstart"; REAL=""; COUNT=24; EPOCHS=12
while [ $# -gt 0 ]; do
  case "$1" in
    --real) REAL="$2"; shift 2 ;;
    --out) OUT="$2"; shift 2 ;;
    --count) COUNT="$2"; shift 2 ;;
    --epochs) EPOCHS="$2"; shift 2 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "quickstart: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
# shellcheck source=pipelines/_install.sh
source "$ROOT/pipelines/_install.sh"
cd "$ROOT"
if [ -z "$REAL" ] && [ -f "$ROOT/../shared/real-sample/height_map.npy" ]; then REAL="$ROOT/../shared/real-sample"; fi
if [ -n "$REAL" ] && [ ! -d "$REAL" ]; then echo "quickstart: --real folder not found: $REAL" >&2; exit 2; fi

echo "== 1/4 generating $COUNT synthetic samples from assets/meshes"
fppsim generate --meshes assets/meshes --out "$OUT/synthetic" --count "$COUNT" --seed 0 --workers 2

echo "== 2/4 training a tiny UHRNet on CPU ($EPOCHS epochs at 176 x 320)"
REAL_ARGS=()
if [ -n "$REAL" ]; then
  n_real=$(python -c "import sys; from uhrnet.data.datasets import FigshareArrays; print(len(FigshareArrays(sys.argv[1])))" "$REAL")
  # the reference 80/10/10 split needs at least 6 samples; a single real sample can only be trained on
  if [ "$n_real" -ge 6 ]; then REAL_ARGS=(--real "$REAL"); else REAL_ARGS=(--real "$REAL" --real-split train); fi
  echo "   real data: $REAL ($n_real samples)"
fi
RESUME=(); [ -f "$OUT/run/last.pt" ] && RESUME=(--resume)
uhrnet train --synthetic "$OUT/synthetic" "${REAL_ARGS[@]}" --model uhrnet --base-channels 8 --resize 176x320 \
  --epochs "$EPOCHS" --batch-size 2 --lr 2e-3 --seed 0 --out "$OUT/run" "${RESUME[@]}"

echo "== 3/4 evaluating on the synthetic test split"
uhrnet evaluate "$OUT/run" --out "$OUT/report"

echo "== 4/4 predicting one fringe image"
uhrnet predict "$OUT/run" "$OUT/synthetic/000000/fringe.png" --rig assets/default_rig.json --out "$OUT/predict"

cat <<EOT

Done. Where everything went:
  synthetic dataset  $OUT/synthetic        (one folder per sample, manifest.jsonl)
  preview            $OUT/synthetic/preview.png   (fringe | height | mask)
  training run       $OUT/run              (history.csv, history.png, best.pt, last.pt)
  evaluation         $OUT/report           (results.md, results.csv, results.json, figures/)
  prediction         $OUT/predict          (height .npy/.tif in mm from the fringe phase at the chosen orders, the network's own, colour PNG, PLY, refine.json)
Activate the environment with: source .venv/bin/activate
EOT
