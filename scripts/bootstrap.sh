#!/usr/bin/env bash
# Idempotent set-up: creates .venv at the repository root, installs the pinned
# dependencies and the three packages (editable). Safe to run again; does nothing
# when requirements.txt and the package manifests have not changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
py="${PYTHON:-python3}"
venv="$root/.venv"
stamp="$venv/.dvt-bootstrap-stamp"
want="$(cat requirements.txt src/*/setup.py src/*/setup.cfg | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/python" ]; then
  exit 0
fi
echo "bootstrap: setting up $venv" >&2
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade "pip>=24" >&2
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.txt >&2
for pkg in dvt_model dvt_driver dvt_identify; do
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation --config-settings editable_mode=compat -e "src/$pkg" >&2
done
"$venv/bin/python" -c "import rclpy, sensor_msgs.msg, rosbags, scipy, dvt_model, dvt_driver, dvt_identify" >&2
echo "$want" > "$stamp"
echo "bootstrap: done" >&2
