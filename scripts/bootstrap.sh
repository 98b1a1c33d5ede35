#!/usr/bin/env bash
# Idempotent set-up: creates .venv at the repository root, installs the pinned runtime
# dependencies (requirements.txt) and the three packages (editable); with --dev also the test
# and tooling dependencies (requirements-dev.txt: pytest, ruff, mypy, colcon, ...). Safe to
# run again; does nothing when the requirement files and the package manifests have not
# changed. Usage: scripts/bootstrap.sh [--dev]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
py="${PYTHON:-python3}"
venv="$root/.venv"
stamp="$venv/.dvt-bootstrap-stamp"
dev_stamp="$venv/.dvt-bootstrap-dev-stamp"
dev=0
case "${1:-}" in
  --dev) dev=1 ;;
  "") ;;
  *) echo "bootstrap: unknown option '$1' (expected --dev or nothing)" >&2; exit 2 ;;
esac
# tests/test_multihost.py makes network namespaces with `ip` (iproute2): install it when
# missing and we are root (otherwise that test skips, saying why)
if ! command -v ip >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2; } \
    >/dev/null 2>&1 || echo "bootstrap: could not install iproute2 (test_multihost skips)" >&2
fi
want="$(cat requirements.txt src/*/setup.py src/*/setup.cfg | sha256sum | cut -d' ' -f1)"
want_dev="$(cat requirements-dev.txt | sha256sum | cut -d' ' -f1)"
runtime_ok=0
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/python" ]; then
  runtime_ok=1
fi
dev_ok=0
if [ -f "$dev_stamp" ] && [ "$(cat "$dev_stamp")" = "$want_dev" ]; then
  dev_ok=1
fi
if [ "$runtime_ok" = 1 ] && { [ "$dev" = 0 ] || [ "$dev_ok" = 1 ]; }; then
  exit 0
fi
echo "bootstrap: setting up $venv (log: $venv/bootstrap.log)" >&2
log="$(mktemp)"
quiet() {  # run a set-up step; its output goes to the log, shown only if the step fails
  if ! "$@" >>"$log" 2>&1; then
    echo "bootstrap: failed: $*" >&2
    tail -n 60 "$log" >&2
    exit 1
  fi
}
[ -x "$venv/bin/python" ] || quiet "$py" -m venv "$venv"
pipq=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check)
quiet "${pipq[@]}" --upgrade "pip>=24"
if [ "$dev" = 1 ]; then
  quiet "${pipq[@]}" -r requirements.txt -r requirements-dev.txt
else
  quiet "${pipq[@]}" -r requirements.txt
fi
for pkg in dvt_model dvt_identify dvt_driver; do  # dependency order (dvt_driver.system uses dvt_identify)
  quiet "${pipq[@]}" --no-deps --no-build-isolation --config-settings editable_mode=compat -e "src/$pkg"
done
quiet "$venv/bin/python" -c "import rclpy, sensor_msgs.msg, rosbags, scipy, dvt_model, dvt_driver, dvt_identify"
mv "$log" "$venv/bootstrap.log"
echo "$want" > "$stamp"
if [ "$dev" = 1 ]; then echo "$want_dev" > "$dev_stamp"; fi
echo "bootstrap: done" >&2
