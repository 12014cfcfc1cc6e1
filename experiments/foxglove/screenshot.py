"""Screenshot Foxglove Studio (web) watching `fpe view` live: the sample drive on the oval.

Starts `fpe view data/samples/drive.mcap --config fit/sim-oval.json --waypoints
data/tracks/oval.csv --foxglove PORT --loop`, opens the Foxglove Studio web app served at
`--studio URL` in a headless Chromium with the WebSocket data source
(`?ds=foxglove-websocket&ds.url=ws://127.0.0.1:...`) and a layout of one 3D panel (display
frame `map`, seen from above, framed on `--box` or the whole track; `/track`, `/observations`,
the predicted path and the ellipses turned on), saves a PNG `--at` seconds into the replay and
stops the browser and `fpe view`.

Studio 1.x asks for the protocol under its old name, `foxglove.websocket.v1`, which the
foxglove-sdk server of `fpe view` refuses (it serves the same protocol as `foxglove.sdk.v1`), so
by default Studio connects to the relay of `ws_relay.py` (beside this script) on `--relay-port`,
which accepts the old name and passes every frame unchanged to `fpe view`; `--relay-port 0`
connects straight to `fpe view` (for a viewer that speaks `foxglove.sdk.v1`).

It builds nothing: the user serves a Foxglove Studio web build (tested: v1.86.0, the
open-source app's `yarn web:build:prod` output, served with `python -m http.server -b 127.0.0.1
8080`). The layout reaches Studio the way its web app keeps one between visits, in
`localStorage["studio.layout"]`, written before the page's own scripts run. The moment in the
picture is only roughly `--at`: a screenshot of the software-rendered page takes a second or more.

Needs, outside the project's dependencies: Chromium and its driver (Debian: `apt-get install
chromium chromium-driver`), selenium (`.venv/bin/pip install selenium`) and websockets (in the
`dev` extra).

    .venv/bin/python experiments/foxglove/screenshot.py --studio http://127.0.0.1:8080/ \\
        --box 9.5,-1.3,25.8,9.0 --at 16 --out docs/images/foxglove_studio.png --force
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from ws_relay import start_relay  # beside this script

from fpe_jax.io import load_waypoints

REPO = Path(__file__).resolve().parents[2]
FPE = str(Path(sys.executable).with_name("fpe"))
LOG = REPO / "data" / "samples" / "drive.mcap"
CONFIG = REPO / "fit" / "sim-oval.json"
WAYPOINTS = REPO / "data" / "tracks" / "oval.csv"
PANEL = "3D!fpe"
MIN_PAGE_S = 4.0  # time Studio takes to load, connect and subscribe here


def layout(box_m: np.ndarray, aspect: float) -> dict:
    """Studio's layout data: one 3D panel in the map frame, orthographic from above, its view
    (`distance` = visible height [m] in that mode) framing `box_m` ((2, 2): the lower-left and
    upper-right x, y corners [m]) in a panel of width/height `aspect`."""
    lo, hi = box_m
    centre_m = (lo + hi) / 2
    height_m = float(max(hi[1] - lo[1], (hi[0] - lo[0]) / aspect))
    topics = {
        "/track": {"visible": True},
        "/observations": {"visible": True},
        "/predictions/opp/ellipses": {"visible": True},
        "/predictions/opp/path": {
            "visible": True,
            "type": "arrow",
            "arrowScale": [0.35, 0.07, 0.07],
        },
    }
    grid = {
        "visible": True,
        "frameLocked": True,
        "label": "Grid (1 m)",
        "instanceId": "grid",
        "layerId": "foxglove.Grid",
        "size": 40,
        "divisions": 40,
        "lineWidth": 0.5,
        "color": "#3a4a5c",
        "position": [float(centre_m[0]), float(centre_m[1]), 0.0],
        "rotation": [0, 0, 0],
        "order": 1,
    }
    panel = {
        "cameraState": {
            "perspective": False,
            "distance": height_m,
            "phi": 0,
            "thetaOffset": 0,
            "target": [0, 0, 0],
            "targetOffset": [float(centre_m[0]), float(centre_m[1]), 0],
            "targetOrientation": [0, 0, 0, 1],
            "fovy": 45,
            "near": 0.5,
            "far": 5000,
        },
        "followMode": "follow-none",
        "followTf": "map",
        "scene": {"transforms": {"showLabel": False}},
        "topics": topics,
        "layers": {"grid": grid},
        "publish": {"type": "point"},
    }
    return {
        "configById": {PANEL: panel},
        "globalVariables": {},
        "userNodes": {},
        "layout": PANEL,
    }


def start_view(port: int) -> subprocess.Popen:
    """`fpe view` serving the sample drive on `port`, returned once it is listening (its replay
    starts then); its messages go on to this script's stderr."""
    cmd = [FPE, "view", str(LOG), "--config", str(CONFIG), "--waypoints", str(WAYPOINTS)]
    cmd += ["--foxglove", str(port), "--loop"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    for line in proc.stderr:
        sys.stderr.write(line)
        if line.startswith("serving Foxglove"):
            copy = lambda: sys.stderr.writelines(proc.stderr)  # noqa: E731
            threading.Thread(target=copy, daemon=True).start()
            return proc
    proc.wait()
    raise SystemExit(f"fpe view exited with status {proc.returncode} before serving")


def stop(proc: subprocess.Popen) -> None:
    """Ctrl-C for `fpe view` (it closes its server); SIGTERM if it does not end (a process
    started in the background may ignore SIGINT)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.terminate()
            proc.wait()


def browse(args, url: str, layout_json: str, replay_start: float) -> None:
    """Open `url` in headless Chromium with `layout_json` as Studio's stored layout; save the
    page as a PNG `args.at` seconds after `replay_start` (time.monotonic() of the replay's
    start)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = args.chromium
    width, height = args.size
    for flag in (
        "--headless=new",
        f"--window-size={width},{height}",
        "--force-device-scale-factor=1",
        "--hide-scrollbars",
        # WebGL without a GPU: the software rasteriser behind ANGLE
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist",
    ):
        opts.add_argument(flag)
    if os.geteuid() == 0:  # Chromium refuses to start its sandbox as root
        opts.add_argument("--no-sandbox")
    driver = webdriver.Chrome(options=opts, service=Service(args.chromedriver))
    try:
        # the page's own scripts read the layout from localStorage at start-up
        script = f"localStorage.setItem('studio.layout', {json.dumps(layout_json)});"
        driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": script})
        # the page's size, whatever the headless window's frame takes
        metrics = {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
        driver.get(url)
        wait_s = replay_start + args.at - time.monotonic()
        if wait_s < MIN_PAGE_S:
            print(f"--at {args.at}: the page has only {wait_s:.1f} s to connect", file=sys.stderr)
        time.sleep(max(wait_s, 0.0))
        Path(args.out).write_bytes(driver.get_screenshot_as_png())
    finally:
        driver.quit()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--studio", required=True, help="URL of a served Foxglove Studio web build")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--force", action="store_true", help="replace --out if it exists")
    ap.add_argument("--port", type=int, default=8765, help="fpe view's WebSocket port")
    ap.add_argument(
        "--relay-port",
        type=int,
        default=8766,
        help="port of the subprotocol relay Studio connects to (0: straight to fpe view, for a "
        "viewer that speaks foxglove.sdk.v1)",
    )
    ap.add_argument(
        "--at",
        type=float,
        default=16.0,
        help="when to take the picture, seconds into the replay (default 16; the drive repeats)",
    )
    ap.add_argument(
        "--size",
        type=lambda s: tuple(int(v) for v in s.split("x")),
        default=(1400, 800),
        help="browser window WIDTHxHEIGHT in pixels (default 1400x800)",
    )
    ap.add_argument(
        "--box",
        type=lambda s: [float(v) for v in s.split(",")],
        help="X0,Y0,X1,Y1: the map-frame rectangle [m] to show (default: the whole track)",
    )
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--chromedriver", default="/usr/bin/chromedriver")
    args = ap.parse_args()
    if Path(args.out).exists() and not args.force:
        raise SystemExit(f"{args.out} exists; --force replaces it")
    if not Path(args.out).resolve().parent.is_dir():
        raise SystemExit(f"{args.out}: no folder {Path(args.out).parent}")

    width, height = args.size
    # the 3D panel is the window less Studio's app bar and panel toolbar (75 px) and its
    # settings sidebar (320 px), which stays open to show the topics
    if args.box is None:
        xy_m = load_waypoints(WAYPOINTS).xy_m
        box_m = np.stack([xy_m.min(axis=0) - 0.6, xy_m.max(axis=0) + 0.6])
    else:
        box_m = np.asarray(args.box, dtype=float)
        if box_m.shape != (4,) or not (box_m[0] < box_m[2] and box_m[1] < box_m[3]):
            raise SystemExit(f"--box {args.box}: expected X0,Y0,X1,Y1 with X0 < X1, Y0 < Y1")
        box_m = box_m.reshape(2, 2)
    data = layout(box_m, aspect=(width - 322) / (height - 75))
    upstream = f"ws://127.0.0.1:{args.port}"
    ws = f"ws://127.0.0.1:{args.relay_port}" if args.relay_port else upstream
    url = f"{args.studio}{'&' if '?' in args.studio else '?'}ds=foxglove-websocket&ds.url={ws}"
    view = start_view(args.port)
    replay_start = time.monotonic()
    try:
        relay = start_relay(args.relay_port, upstream) if args.relay_port else None
        try:
            browse(args, url, json.dumps(data), replay_start)
        finally:
            if relay is not None:
                relay.set()
    finally:
        stop(view)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
