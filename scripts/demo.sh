#!/usr/bin/env bash
# The demo: set-up (idempotent), then the full chain on the simulated plant.
# Usage: scripts/demo.sh [OUTDIR]   (default: demo-out)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/bootstrap.sh
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( $$ % 100 + 100 ))}"
exec "$root/.venv/bin/python" -m dvt_driver.system.demo "${1:-demo-out}"
