#!/usr/bin/env bash
# Figures with provenance: runs the named commands and writes docs/results/<name>.json (command,
# commit, date, machine, figures). Usage: scripts/results.sh NAME... | all  (see scripts/results.py)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
exec "$root/.venv/bin/python" "$root/scripts/results.py" "$@"
