#!/usr/bin/env bash
# Re-create the committed recordings in bags/ with the real chain, in real time:
#   dvt-launch sim = dvt-plant (simulated controller on a pty) -> dvt_driver_node -> dvt-recorder,
#   with dvt-experiment sending the commands. Each bag gets truth.yaml (the plant's hidden
#   effects) and run.yaml (how it was made) from the launcher. About 8 minutes.
#   The effect presets draw their magnitudes from the plant seed (--seed N: draw N,
#   dvt_driver.plant.hidden.draw): truth.yaml holds the drawn values (hidden) and the draw
#   (hidden_draw); the tests compare what the identifier finds with them.
#
# Usage: scripts/make_bags.sh [OUTDIR [RUN ...]]   (default: bags, every run below)
#
# A run is retried (up to 3 attempts) when the launcher reports a failure, e.g. a driver trip
# or more than MAX_MISSING samples missing from the bag (a busy machine); existing bags of the
# same name are replaced only by a successful run. The total size must stay under 30 MB.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="${1:-$root/bags}"
shift || true
bin="$root/.venv/bin"
[ -x "$bin/dvt-launch" ] || bash "$root/scripts/bootstrap.sh"
# an isolated ROS graph: a domain above the 1..200 the topic-level tests use, this machine only
export ROS_DOMAIN_ID="${DVT_BAGS_DOMAIN_ID:-$((201 + $$ % 30))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
MAX_MISSING="${MAX_MISSING:-25}"
LIMIT_BYTES=$((30 * 1000 * 1000))

# The thesis holds the sun at 1500, 1600, 2000 and 2400 rpm. The drive's speed loop rides up to
# ~10 rpm above its set-point (encoder quantisation, the overshoot when band 1 releases); the
# driver trips 2 % above max_sun_speed, so a 2400 rpm hold is fine. THESIS_TOP_RPM overrides it.
THESIS_TOP_RPM="${THESIS_TOP_RPM:-2400}"

# name | dvt-launch sim arguments (the bags/README.md table lists the same)
RUNS=(
  "thesis-none|--experiment thesis --experiment-set speeds_rpm=[1500,1600,2000,$THESIS_TOP_RPM] --hidden none --seed 1"
  "ident-none-1|--experiment ident --experiment-seed 1 --hidden none --seed 11 --no-model"
  "ident-none-2|--experiment ident --experiment-seed 2 --hidden none --seed 12 --no-model"
  "ident-coulomb|--experiment ident --experiment-seed 3 --hidden coulomb --seed 13 --no-model"
  "ident-stribeck|--experiment ident --experiment-seed 4 --hidden stribeck --seed 14 --no-model"
  "ident-windage|--experiment ident --experiment-seed 5 --hidden windage --seed 15 --no-model"
  "ident-backlash|--experiment ident --experiment-seed 6 --hidden backlash --seed 16 --no-model"
  "ident-delay|--experiment ident --experiment-seed 7 --hidden delay --seed 17 --no-model"
  "ident-wet_brake|--experiment ident_shifts --experiment-seed 8 --hidden wet_brake --seed 18 --no-model"
)
# 1 kHz identification runs record the contract topics, the commands and the diagnostics
# (the model node's output is not needed: dvt-replay regenerates it); the 62.5 Hz thesis
# replica also records the live model node's prediction and residual.
IDENT_TOPICS=(--record-topics /dvt/joint_states /dvt/currents '/dvt/cmd/*' /diagnostics)

mkdir -p "$out"
logroot="$(mktemp -d /tmp/dvt-make-bags-XXXXXX)"
echo "make_bags: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, logs in $logroot" >&2

selected=("$@")
want() {
  [ ${#selected[@]} -eq 0 ] && return 0
  local s
  for s in "${selected[@]}"; do [ "$s" = "$1" ] && return 0; done
  return 1
}

for entry in "${RUNS[@]}"; do
  name="${entry%%|*}"
  read -r -a args <<< "${entry#*|}"
  want "$name" || continue
  extra=()
  [[ "$name" == ident-* ]] && extra=("${IDENT_TOPICS[@]}")
  ok=0
  for attempt in 1 2 3; do
    # record under the final name (the recorder names the MCAP file after the directory)
    tmp="$logroot/$name-$attempt/bag/$name"
    mkdir -p "$(dirname "$tmp")"
    echo "make_bags: $name (attempt $attempt): dvt-launch sim ${args[*]} ${extra[*]}" >&2
    if "$bin/dvt-launch" sim "${args[@]}" "${extra[@]}" --record "$tmp" \
        --max-missing "$MAX_MISSING" --log-dir "$logroot/$name-$attempt/logs"; then
      rm -rf "${out:?}/$name"
      mv "$tmp" "$out/$name"
      ok=1
      break
    fi
    echo "make_bags: $name attempt $attempt failed (logs: $logroot/$name-$attempt/logs)" >&2
  done
  [ "$ok" = 1 ] || { echo "make_bags: $name failed 3 times" >&2; exit 1; }
done

"$bin/python" - "$out" <<'EOF'
import sys
from pathlib import Path

from dvt_model.recording import read_run, sample_period

out = Path(sys.argv[1])
for bag in sorted(p for p in out.iterdir() if (p / "metadata.yaml").exists()):
    run = read_run(bag)
    size = sum(f.stat().st_size for f in bag.iterdir())
    print(f"{bag.name:18s} {run.n:6d} samples {run.duration:6.1f} s "
          f"{1 / sample_period(run):7.1f} Hz {size / 1e6:5.2f} MB "
          f"truth={'yes' if (bag / 'truth.yaml').exists() else 'NO'}")
EOF
total=$(find "$out" -type f -printf '%s\n' | awk '{s += $1} END {print s + 0}')
echo "make_bags: total $(awk -v b="$total" 'BEGIN {printf "%.1f", b / 1e6}') MB in $out" >&2
if [ "$total" -gt "$LIMIT_BYTES" ]; then
  echo "make_bags: over the 30 MB limit" >&2
  exit 1
fi
