#!/usr/bin/env bash
# Install everything (idempotent), then run the test suite without the tests marked slow (under 10 minutes on
# 2 cores). Extra arguments go to pytest: -m slow runs the slow ones (CI runs both), -m 'slow or not slow' all.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=pipelines/_install.sh
source "$ROOT/pipelines/_install.sh"
cd "$ROOT"
exec python -m pytest -q -m "not slow" "$@"
