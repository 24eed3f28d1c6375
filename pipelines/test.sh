#!/usr/bin/env bash
# Install everything (idempotent), then run the test suite. Extra arguments go to pytest.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=pipelines/_install.sh
source "$ROOT/pipelines/_install.sh"
cd "$ROOT"
exec python -m pytest -q "$@"
