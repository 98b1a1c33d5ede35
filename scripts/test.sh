#!/usr/bin/env bash
# The test command: set-up (idempotent), lint, type check, unit and topic-level tests.
# Usage: scripts/test.sh [extra pytest args]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/bootstrap.sh --dev
export PATH="$root/.venv/bin:$PATH"
echo "== ruff" >&2
ruff check src tests examples
echo "== mypy" >&2
mypy src/dvt_model/dvt_model src/dvt_driver/dvt_driver src/dvt_identify/dvt_identify
lint-imports  # the dependency rules of pyproject.toml [tool.importlinter]
echo "== pytest" >&2
# each topic-level test picks its own ROS_DOMAIN_ID; keep discovery on this machine
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
exec pytest src/dvt_model/test src/dvt_driver/test src/dvt_identify/test tests "$@"
