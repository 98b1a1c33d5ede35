#!/usr/bin/env bash
# EMPS real-data example: import both EMPS records into rosbag2/MCAP bags, then identify by the
# benchmark's own protocol (simulated position, 20-sample initialisation window), every choice
# on the estimation record, the other record read only as the test; then recompute the figure
# independently beside the published ones with examples/emps/benchmark.py.
#
#   examples/emps/run.sh OUTDIR
#
# EMPS_DIR overrides where the data are (default: ../shared/data/emps relative to the repository
# root). Nothing from the data folder is copied into the repository; bags and report go to OUTDIR.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
if [ $# -ne 1 ]; then
  echo "usage: $0 OUTDIR" >&2
  exit 2
fi
out="$1"
emps="${EMPS_DIR:-$root/../shared/data/emps}"
for f in emps_estimation.npz emps_validation.npz; do
  if [ ! -f "$emps/$f" ]; then
    echo "run.sh: error: $emps/$f not found (set EMPS_DIR to the folder with the EMPS records)" >&2
    exit 2
  fi
done
"$root/scripts/bootstrap.sh"
bin="$root/.venv/bin"
mkdir -p "$out"
for rec in estimation validation; do
  # force F = gtau * vir [N], the carriage's position and its filtered derivative: mapping.yaml
  "$bin/dvt-import" "$emps/emps_$rec.npz" --out "$out/bags/emps_$rec" --force \
    --mapping "$here/mapping.yaml"
done
# The benchmark's figure, every choice made on the estimation record (its last 30 % held out
# for the choice of effects); the test record is read after every choice, initial states from
# the first 20 samples of every record as the benchmark allows.
"$bin/dvt-identify" "$out/bags/emps_estimation" --select-on holdout \
  --test "$out/bags/emps_validation" --init-window 20 --description emps-position --out "$out"
# An independent recomputation of the figure, the published models and baselines beside it.
"$bin/python" "$here/benchmark.py" --data "$emps" --report "$out/report.json" --out "$out" \
  > /dev/null
echo "report: $out/report.md ($out/report.json)" >&2
echo "benchmark: $out/benchmark.md ($out/benchmark.json)" >&2
