#!/usr/bin/env bash
# The test command: set-up (idempotent), lint, type check, unit and topic-level tests.
# Usage: scripts/test.sh [--fast] [extra pytest args]
#   (no option)  the full suite (what .ci/run calls): every test, topic-level and slow ones too.
#   --fast       the same set-up, lint and type check, then only the unit and offline tests:
#                pytest -m "not ros and not slow" (no topic-level ROS process chain, none of the
#                statistical or benchmark runs); a few minutes on two cores.
set -euo pipefail
fast=0
if [ "${1:-}" = "--fast" ]; then
  fast=1
  shift
fi
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
if [ "$fast" = 1 ]; then
  exec pytest src/dvt_model/test src/dvt_driver/test src/dvt_identify/test tests \
    -m "not ros and not slow and not peer" "$@"
fi
# the optional CasADi peer's fits (marker peer) take tens of minutes each: `pytest -m peer`;
# the 30 longest tests are listed at the end (where the suite's time goes)
exec pytest src/dvt_model/test src/dvt_driver/test src/dvt_identify/test tests -m "not peer" \
  --durations=30 "$@"
