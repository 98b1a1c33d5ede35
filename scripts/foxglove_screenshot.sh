#!/usr/bin/env bash
# Re-make docs/img/foxglove.png: a real screenshot of a Foxglove viewer showing the shipped
# layout (docs/foxglove/dvt-layout.json) on a real demo run of the suite.
#
# NOT part of set-up, the tests or CI: a one-off documentation tool. It needs node/npm and a
# Chromium, and downloads (into $WORK only, nothing into the project or its venv):
#   - @foxglove/studio-base@1.48.0 (npm, MPL-2.0): open-source Foxglove Studio, whose npm package
#     carries a prebuilt web bundle (assets/index.js); react/react-dom 17.0.2 (npm) for it;
#   - puppeteer-core (npm) to drive the browser (no browser download: it uses the system one);
#   - Debian's `chromium` (apt-get install, system-wide) if no chromium is found.
# The viewer is that bundle's <App> hosted by a ~60-line page written below (in-memory layout
# storage holding our layout as id "dvt", data source from the URL: ?ds=remote-file&ds.url=... or
# ?ds=foxglove-websocket&ds.url=ws://...), served from $WORK on 127.0.0.1 by a small
# Range-capable Python server, and shot headless at 1600x1000 (dark theme, left sidebar closed).
#
# Usage: scripts/foxglove_screenshot.sh [--bag DIR | --live] [--at SECONDS] [--out PNG]
#   (default)   record a fresh `dvt-launch sim --experiment shifts` run (real chain: simulated
#               plant -> driver -> model node -> recorder, about 40 s), convert it with
#               `dvt-foxglove --bag` (every channel the live bridge serves: noise band, state...)
#               and open that MCAP as a file, seeked to --at seconds after its start (default:
#               21, or the end of a shorter file); the plots show the 20 s before that time;
#   --bag DIR   the same with an existing bag instead of a fresh run (e.g. bags/thesis-none);
#   --live      the viewer connects to ws://127.0.0.1:WS_PORT, then `dvt-launch sim --experiment
#               shifts --foxglove` runs, and the shot is taken while the experiment stops the
#               drive (the live plots' sliding 20 s window). Studio 1.48 predates the bridge's
#               subprotocol name foxglove.sdk.v1: sdk-alias.js (below) offers it too. On a busy
#               machine the browser competes with the 1 kHz chain (lost samples in the plots).
# Environment: WORK (default /tmp/dvt-foxglove-screenshot), CHROMIUM (browser binary),
#   PORT (http, default 8123), WS_PORT (bridge, default 8765).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORK="${WORK:-/tmp/dvt-foxglove-screenshot}"
PORT="${PORT:-8123}"
WS_PORT="${WS_PORT:-8765}"
out="$root/docs/img/foxglove.png"
mode=run; bag=""; at=21
while [ $# -gt 0 ]; do
  case "$1" in
    --bag) mode=bag; bag="$(cd "$2" && pwd)"; shift 2 ;;
    --live) mode=live; shift ;;
    --at) at="$2"; shift 2 ;;
    --out) out="$(realpath -m "$2")"; shift 2 ;;
    *) echo "usage: $0 [--bag DIR | --live] [--at SECONDS] [--out PNG]" >&2; exit 2 ;;
  esac
done
bin="$root/.venv/bin"
[ -x "$bin/dvt-launch" ] || { echo "no $bin/dvt-launch: run scripts/bootstrap.sh first" >&2; exit 1; }
command -v npm >/dev/null || { echo "needs node and npm (apt-get install nodejs npm)" >&2; exit 1; }
if [ -z "${CHROMIUM:-}" ]; then
  CHROMIUM="$(command -v chromium || command -v chromium-browser || true)"
  if [ -z "$CHROMIUM" ]; then
    echo "installing Debian's chromium (system-wide)"
    apt-get update -qq && apt-get install -y -qq chromium >/dev/null
    CHROMIUM="$(command -v chromium)"
  fi
fi
export CHROMIUM
# an isolated ROS graph, as scripts/make_bags.sh: above the 1..200 the topic-level tests use
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((201 + $$ % 30))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

# ---------------------------------------------------------------- the viewer and the driver
mkdir -p "$WORK/web" "$WORK/pkgs" "$WORK/driver"
fetch() {  # fetch NAME@VERSION DIR: unpack an npm package into $WORK/web/DIR (once)
  [ -e "$WORK/web/$2/package.json" ] && return
  local tgz
  tgz="$(cd "$WORK/pkgs" && npm pack --silent "$1" 2>/dev/null | tail -n 1)"
  mkdir -p "$WORK/web/$2"
  tar xzf "$WORK/pkgs/$tgz" -C "$WORK/web/$2" --strip-components=1
}
fetch @foxglove/studio-base@1.48.0 studio-base
fetch react@17.0.2 react
fetch react-dom@17.0.2 react-dom
if [ ! -d "$WORK/driver/node_modules/puppeteer-core" ]; then
  (cd "$WORK/driver" && echo '{"private":true}' >package.json &&
   PUPPETEER_SKIP_DOWNLOAD=1 nice -n 10 npm install --silent --no-audit --no-fund puppeteer-core@24.43.1)
fi
cp "$root/docs/foxglove/dvt-layout.json" "$WORK/web/layout.json"

cat >"$WORK/web/index.html" <<'EOF'
<!doctype html>
<html><head><meta charset="utf-8"><title>Foxglove Studio 1.48 (open source)</title>
<style>html,body,#root{margin:0;height:100%;width:100%;overflow:hidden}</style>
</head><body><div id="root"></div>
<script src="react/umd/react.production.min.js"></script>
<script src="react-dom/umd/react-dom.production.min.js"></script>
<script>window["react"] = window.React; window["react-dom"] = window.ReactDOM;</script>
<script src="sdk-alias.js"></script>
<script src="studio-base/assets/index.js"></script>
<script src="main.js"></script>
</body></html>
EOF
cat >"$WORK/web/sdk-alias.js" <<'EOF'
// Live only. Studio 1.48 speaks the WebSocket subprotocol "foxglove.websocket.v1"; foxglove-sdk
// servers (our bridge) accept only its renamed, so far identical, successor "foxglove.sdk.v1"
// (newer Foxglove and Lichtblick offer both names). Studio opens its socket in a worker: offer
// the new name too, and report the negotiated one under the old name.
(() => {
  const OLD = "foxglove.websocket.v1", NEW = "foxglove.sdk.v1";
  const post = Worker.prototype.postMessage;
  Worker.prototype.postMessage = function (msg, ...rest) {
    const p = msg && msg.type === "open" && msg.data && msg.data.protocols;
    if (Array.isArray(p) && p.includes(OLD)) msg = { ...msg, data: { ...msg.data, protocols: [...p, NEW] } };
    return post.call(this, msg, ...rest);
  };
  const onmessage = Object.getOwnPropertyDescriptor(Worker.prototype, "onmessage");
  Object.defineProperty(Worker.prototype, "onmessage", {
    configurable: true, get() { return onmessage.get.call(this); },
    set(fn) {
      onmessage.set.call(this, typeof fn !== "function" ? fn : (ev) => fn.call(this,
        ev.data && ev.data.type === "open" && ev.data.protocol === NEW
          ? new MessageEvent("message", { data: { ...ev.data, protocol: OLD } }) : ev));
    },
  });
})();
EOF
cat >"$WORK/web/main.js" <<'EOF'
// Hosts @foxglove/studio-base's <App> (its UMD bundle puts its exports on window).
(async () => {
  const layoutData = await (await fetch("layout.json")).json();
  const layouts = new Map([["dvt", {
    id: "dvt", name: "dvt-layout", permission: "CREATOR_WRITE",
    baseline: { data: layoutData, savedAt: undefined }, working: undefined, syncInfo: undefined,
  }]]);
  const layoutStorage = {
    async list() { return [...layouts.values()]; },
    async get(_ns, id) { return layouts.get(id); },
    async put(_ns, layout) { layouts.set(layout.id, layout); return layout; },
    async delete(_ns, id) { layouts.delete(id); },
    async migrateUnnamespacedLayouts() {},
    async importLayouts() {},
  };
  const settings = new Map([
    ["colorScheme", new URLSearchParams(location.search).get("theme") || "dark"],
    ["ui.open-dialog-startup", false], ["hideSignInPrompt", true], ["timezone", "UTC"],
    ["telemetry.telemetryEnabled", false], ["telemetry.crashReportingEnabled", false],
  ]);
  const listeners = new Map();
  const appConfiguration = {
    get: (k) => settings.get(k),
    set: async (k, v) => { settings.set(k, v); (listeners.get(k) || []).forEach((cb) => cb(v)); },
    addChangeListener: (k, cb) => listeners.set(k, [...(listeners.get(k) || []), cb]),
    removeChangeListener: (k, cb) => listeners.set(k, (listeners.get(k) || []).filter((c) => c !== cb)),
  };
  const dataSources = [new FoxgloveWebSocketDataSourceFactory(), new McapLocalDataSourceFactory(),
                       new RemoteDataSourceFactory()];
  await initI18n();
  await waitForFonts();
  ReactDOM.render(React.createElement(App, {
    deepLinks: [window.location.href], appConfiguration, dataSources, layoutStorage,
    extensionLoaders: [], enableLaunchPreferenceScreen: false, enableGlobalCss: true,
  }), document.getElementById("root"));
})().catch((e) => console.error("host page failed", e));
EOF
cat >"$WORK/serve.py" <<'EOF'
# Static files from argv[1] on 127.0.0.1:argv[2], with the HTTP Range requests that the
# viewer's remote-file source uses.
import http.server, os, re, sys
class Handler(http.server.SimpleHTTPRequestHandler):
    def end_headers(self):
        self.send_header("Accept-Ranges", "bytes")
        super().end_headers()
    def do_GET(self):
        path = self.translate_path(self.path)
        m = re.match(r"bytes=(\d*)-(\d*)$", self.headers.get("Range", ""))
        if not m or not os.path.isfile(path):
            return super().do_GET()
        size = os.path.getsize(path)
        if m.group(1):
            start, end = int(m.group(1)), min(int(m.group(2) or size - 1), size - 1)
        else:
            start, end = max(0, size - int(m.group(2))), size - 1
        with open(path, "rb") as f:
            f.seek(start)
            data = f.read(end - start + 1)
        self.send_response(206)
        self.send_header("Content-Type", self.guess_type(path))
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)
    def log_message(self, *args):
        pass
Handler.extensions_map[".wasm"] = "application/wasm"
os.chdir(sys.argv[1])
http.server.ThreadingHTTPServer(("127.0.0.1", int(sys.argv[2])), Handler).serve_forever()
EOF
cat >"$WORK/driver/shot.js" <<'EOF'
// node shot.js URL OUT.png: load the viewer, close the left sidebar, wait for the panels, shoot.
// READY_FILE: touched once the panels are up; GO_FILE: if set, wait for it before the shot,
// else for two equal frames 4 s apart.
const fs = require("fs");
const puppeteer = require("puppeteer-core");
const [url, out] = process.argv.slice(2);
const sleep = (s) => new Promise((r) => setTimeout(r, s * 1000));
(async () => {
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM, headless: true, protocolTimeout: 600000,
    args: ["--no-sandbox", "--disable-dev-shm-usage", "--hide-scrollbars"],
    defaultViewport: { width: 1600, height: 1000, deviceScaleFactor: 1 },
  });
  const page = await browser.newPage();
  page.on("pageerror", (e) => console.log("[page error]", String(e).slice(0, 300)));
  page.on("response", (r) => { if (r.status() >= 400 && !r.url().endsWith("favicon.ico")) console.log("[http]", r.status(), r.url()); });
  await page.goto(url, { waitUntil: "load", timeout: 600000 });
  await page.waitForFunction(() => document.querySelectorAll("canvas").length >= 4, { timeout: 600000 });
  await page.evaluate(() => document.querySelector('[data-sidebar-key][aria-selected="true"]')?.click());
  if (process.env.READY_FILE) fs.writeFileSync(process.env.READY_FILE, "");
  if (process.env.GO_FILE) {
    while (!fs.existsSync(process.env.GO_FILE)) await sleep(0.2);
  } else {  // a file loads in blocks, the plots redraw as they come: wait until the page is still
    let last = null;
    for (let i = 0; i < 100; i++) {
      await sleep(4);
      const now = await page.screenshot({ encoding: "base64" });
      if (now === last) break;
      last = now;
    }
  }
  const empty = await page.evaluate(() => document.body.innerText.match(/Waiting for \/dvt[^\n]*/g));
  if (empty) console.log("panels still waiting:", empty.join("; "));
  await page.screenshot({ path: out });
  console.log("dvt-foxglove-screenshot: wrote", out);
  await browser.close();
})().catch((e) => { console.error(e); process.exit(1); });
EOF

# ---------------------------------------------------------------- serve, run, shoot
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup EXIT
python3 "$WORK/serve.py" "$WORK/web" "$PORT" & pids+=($!)
sleep 1
kill -0 "${pids[0]}" || { echo "cannot serve on 127.0.0.1:$PORT (PORT=... to change)" >&2; exit 1; }
mkdir -p "$(dirname "$out")"
page="http://127.0.0.1:$PORT/index.html?layoutId=dvt"

if [ "$mode" = live ]; then
  rm -f "$WORK/ready" "$WORK/go"
  READY_FILE="$WORK/ready" GO_FILE="$WORK/go" nice -n 5 node "$WORK/driver/shot.js" \
    "$page&ds=foxglove-websocket&ds.url=ws%3A%2F%2F127.0.0.1%3A$WS_PORT" "$out" & shot=$!
  while [ ! -e "$WORK/ready" ]; do kill -0 "$shot" || exit 1; sleep 1; done
  # the shot while the experiment's last phase ("stop", 1.5 s) brakes the drive to zero
  "$bin/dvt-launch" sim --experiment shifts --foxglove --foxglove-port "$WS_PORT" --no-check \
      --duration 60 2>&1 | while IFS= read -r line; do
    echo "$line"
    case "$line" in *"phase stop"*) sleep 1.2; touch "$WORK/go" ;; esac
  done &
  run=$!
  wait "$shot"
  wait "$run"   # the launcher stops every process at the end of the experiment
  exit 0
fi

if [ "$mode" = run ]; then
  bag="$WORK/run-shifts"
  rm -rf "$bag" "$WORK/run-logs"
  "$bin/dvt-launch" sim --experiment shifts --record "$bag" --log-dir "$WORK/run-logs"
fi
"$bin/dvt-foxglove" --bag "$bag" --out "$WORK/web/demo.mcap.tmp"
mv "$WORK/web/demo.mcap.tmp" "$WORK/web/demo.mcap"
seek="$("$bin/python" - "$WORK/web/demo.mcap" "$at" <<'EOF'
import datetime, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    stats = make_reader(f).get_summary().statistics
t = min(stats.message_start_time + float(sys.argv[2]) * 1e9, stats.message_end_time) / 1e9
print(datetime.datetime.fromtimestamp(t, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z")
EOF
)"
nice -n 5 node "$WORK/driver/shot.js" \
  "$page&ds=remote-file&ds.url=http%3A%2F%2F127.0.0.1%3A$PORT%2Fdemo.mcap&time=$seek" "$out"
