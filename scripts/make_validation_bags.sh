#!/usr/bin/env bash
# Write the validation pairs of the committed estimation recordings into bags/ (or OUTDIR):
# bags/ident-coulomb-val and bags/ident-none-val, second runs of the same plant (the drawn
# values in truth.yaml of ident-coulomb / ident-none-1) driven offline through the driver's supervisor
# with experiment seed + 100 and plant seed + 100; zstd-compressed, about 2 MB each.
# They are the validation data of `dvt-bench identify --compare` and tests/test_fit_quality.py.
#
# Usage: scripts/make_validation_bags.sh [OUTDIR [NAME=SOURCE ...]]   (about 15 s)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bin="$root/.venv/bin"
[ -x "$bin/python" ] || bash "$root/scripts/bootstrap.sh"
exec "$bin/python" "$root/scripts/make_validation_bags.py" "$@"
