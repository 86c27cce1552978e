#!/usr/bin/env bash
# Screenshot of a ShadowCorr Rerun recording in Rerun's web viewer, for the exports guide
# (docs/guide/exports.md shows docs/guide/exports-rerun.png, made with the defaults below).
#
#   scripts/screenshot_rerun.sh [BUNDLE] [OUT_PNG]      (defaults: out/sample_bundle, docs/guide/exports-rerun.png)
#   SOURCE=bag scripts/screenshot_rerun.sh [BUNDLE] [OUT_PNG]      (default OUT_PNG: docs/guide/exports-bag.png)
#
# SOURCE=bag exports the ROS 2 bag instead and opens its MCAP file in the same viewer, which reads
# ROS 2 MCAP itself (no blueprint: the viewer's default layout).
#
# Steps: `shadowcorr correspond` and `shadowcorr export --to rrd` in a temporary folder; a
# blueprint with one 3D view of the objects (fused points and oriented boxes) and the camera
# frustums, looking at the objects from above the cameras' side; `rerun --web-viewer` serving
# the recording and the blueprint on 127.0.0.1; headless Chromium, driven over the DevTools
# protocol, opens the viewer, waits WAIT_S seconds (default 30; WebGL runs on SwiftShader, so
# the viewer is slow) and saves the page as a 1600x900 PNG.
#
# Needs: .venv with the viz extra (rerun-sdk) and websockets (the service's uvicorn brings it),
# and Debian's chromium (`apt-get install chromium`). Ports: WEB_PORT (9090) and GRPC_PORT (9876).
set -euo pipefail
cd "$(dirname "$0")/.."
BUNDLE=${1:-out/sample_bundle}
SOURCE=${SOURCE:-rrd}
OUT_PNG=${2:-docs/guide/exports-$([ "$SOURCE" = bag ] && echo bag || echo rerun).png}
WAIT_S=${WAIT_S:-30}
WEB_PORT=${WEB_PORT:-9090}
GRPC_PORT=${GRPC_PORT:-9876}
PY=.venv/bin/python
WORK=$(mktemp -d)
VIEWER_PID=
cleanup() {
  if [ -n "$VIEWER_PID" ]; then kill "$VIEWER_PID" 2>/dev/null || true; fi
  rm -rf "$WORK"
}
trap cleanup EXIT

.venv/bin/shadowcorr correspond "$BUNDLE" --out "$WORK/result.json"
if [ "$SOURCE" = bag ]; then
  .venv/bin/shadowcorr export "$WORK/result.json" "$BUNDLE" "$WORK/bag" --to bag
  INPUTS=("$WORK/bag/bag.mcap")
else
.venv/bin/shadowcorr export "$WORK/result.json" "$BUNDLE" "$WORK/scene.rrd" --to rrd
INPUTS=("$WORK/scene.rrd" "$WORK/view.rbl")

"$PY" - "$WORK/result.json" "$BUNDLE" "$WORK/view.rbl" <<'EOF'
import json
import sys

import numpy as np
import rerun.blueprint as rrb

import shadowcorr
from shadowcorr.bundle import UNIT_IN_METRES
from shadowcorr.export._scene import entity_name

result_path, bundle_path, out = sys.argv[1:4]
result = json.load(open(result_path))
bundle = shadowcorr.load_bundle(bundle_path)
centres = np.array([o["oriented_box"]["center"] for o in result["objects"] if o.get("oriented_box")])
centres = centres * UNIT_IN_METRES[result["units"]]
cameras = np.array([v.pose[:3, 3] for v in bundle.views]) * UNIT_IN_METRES[bundle.units]
target = (centres.min(0) + centres.max(0)) / 2
radius = np.linalg.norm(centres.max(0) - centres.min(0)) / 2
# Look from the cameras' side (the surfaces they saw face it), raised above the ground.
side = cameras.mean(0) - target
side[2] = 0.0
side /= np.linalg.norm(side) or 1.0
eye = target + 1.5 * radius * side + np.array([0.0, 0.0, 1.1 * radius])
view = rrb.Spatial3DView(
    origin="world", name="sample scene: fused points and oriented boxes",
    contents=["+ world/objects/**"] + [f"+ world/cameras/{entity_name(v.name)}" for v in bundle.views],
    eye_controls=rrb.EyeControls3D(position=eye, look_target=target, eye_up=[0.0, 0.0, 1.0]),
)
rrb.Blueprint(view, collapse_panels=True).save("shadowcorr", out)
EOF
fi

# The rerun binary itself (not the Python launcher), so that its id is the one to stop.
RERUN_BIN=$("$PY" -c 'import pathlib, rerun_cli; print(pathlib.Path(rerun_cli.__file__).parent / "rerun")')
BROWSER=/bin/true "$RERUN_BIN" --web-viewer --bind 127.0.0.1 --web-viewer-port "$WEB_PORT" --port "$GRPC_PORT" \
  -j 1 "${INPUTS[@]}" >"$WORK/rerun.log" 2>&1 &
VIEWER_PID=$!
for _ in $(seq 50); do
  grep -q "Hosting a web-viewer" "$WORK/rerun.log" && break
  sleep 0.2
done

"$PY" - "http://127.0.0.1:$WEB_PORT/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A$GRPC_PORT%2Fproxy" \
  "$OUT_PNG" "$WAIT_S" "$WORK/chromium" <<'EOF'
import asyncio
import base64
import json
import pathlib
import subprocess
import sys
import time
import urllib.request

import websockets

url, out_png, wait_s, profile = sys.argv[1], pathlib.Path(sys.argv[2]), float(sys.argv[3]), pathlib.Path(sys.argv[4])
chromium = subprocess.Popen(
    ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
     "--window-size=1600,900", "--hide-scrollbars", "--remote-debugging-address=127.0.0.1",
     "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"],
    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


async def screenshot(ws_url: str) -> bytes:
    async with websockets.connect(ws_url, max_size=64 * 2**20) as ws:
        for n, (method, params) in enumerate([
                ("Emulation.setDeviceMetricsOverride", {"width": 1600, "height": 900, "deviceScaleFactor": 1,
                                                        "mobile": False}),
                ("Page.navigate", {"url": url}),
                ("Page.captureScreenshot", {"format": "png"})]):
            if method == "Page.captureScreenshot":
                await asyncio.sleep(wait_s)  # the wasm viewer loads, connects and renders
            await ws.send(json.dumps({"id": n, "method": method, "params": params}))
            while (reply := json.loads(await ws.recv())).get("id") != n:
                pass
            if "error" in reply:
                raise RuntimeError(f"{method}: {reply['error']}")
        return base64.b64decode(reply["result"]["data"])


try:
    port_file = profile / "DevToolsActivePort"
    deadline = time.monotonic() + 30
    while not (port_file.exists() and port_file.read_text().strip()):
        if time.monotonic() > deadline:
            sys.exit("chromium did not open its DevTools port")
        time.sleep(0.2)
    port = port_file.read_text().split()[0]
    targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json"))
    page = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
    out_png.write_bytes(asyncio.run(screenshot(page)))
    print(f"wrote {out_png}")
finally:
    chromium.terminate()
    chromium.wait(10)
EOF
