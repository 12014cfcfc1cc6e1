"""What one `SceneSink` update costs its caller: an observation plus a 10-step prediction with
its ellipses, for one car, timed per call (time.perf_counter_ns) in three setups:

- mcap: recording to an MCAP file only;
- live: the WebSocket server with one subscribed client that reads everything;
- stalled: the server with one subscribed client that never reads (its queue fills; the SDK
  drops the oldest messages for it), with the MCAP recording on as well.

Each setup runs 3 times (4000 timed calls after 200 untimed ones); the table gives the median
over the runs of each run's p50 and p99. Writes experiments/results/foxglove_sink.md.

    .venv/bin/python experiments/foxglove/sink_timing.py
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from websockets.sync.client import connect

from fpe_jax.node import SceneSink

RESULTS = Path(__file__).resolve().parents[1] / "results" / "foxglove_sink.md"
H, WARM, CALLS, RUNS = 10, 200, 4000, 3


def _subscribe_all(ws, channels: int) -> None:
    """Read serverInfo and advertise messages until `channels` are known; subscribe to them."""
    ids = []
    while len(ids) < channels:
        frame = ws.recv(timeout=5)
        if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
            ids += [c["id"] for c in json.loads(frame)["channels"]]
    subs = [{"id": k + 1, "channelId": cid} for k, cid in enumerate(ids)]
    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


def _update(sink, k: int, t0_ns: int) -> None:
    stamp = t0_ns + k * 25_000_000  # 40 Hz
    steps = stamp + np.arange(1, H + 1) * 100_000_000
    a = 0.01 * k + 0.1 * np.arange(1, H + 1)
    poses = np.column_stack([10 * np.cos(a), 10 * np.sin(a), a + np.pi / 2])
    cov = np.broadcast_to(np.diag([0.04, 0.01]), (H, 2, 2))
    sink.observation("opp", stamp, 10 * np.cos(0.01 * k), 10 * np.sin(0.01 * k), 0.01 * k)
    sink.prediction("opp", stamp, poses, cov, steps)


def run_once(setup: str, tmp: Path) -> np.ndarray:
    mcap = tmp / f"{setup}.{time.monotonic_ns()}.mcap" if setup != "live" else None
    sink = SceneSink(port=0 if setup != "mcap" else None, mcap_path=mcap)
    sink.track(np.column_stack([10 * np.cos(np.linspace(0, 6.2, 600)), np.zeros(600)]))
    t0 = 1_700_000_000 * 10**9
    stop = threading.Event()
    reader, ws = None, None
    try:
        _update(sink, 0, t0)  # creates the four channels
        if setup != "mcap":
            # no keepalive pings: the stalled client would time out on them
            ws = connect(
                f"ws://127.0.0.1:{sink.port}", subprotocols=["foxglove.sdk.v1"], ping_interval=None
            )
            ws.__enter__()
            _subscribe_all(ws, 4)
            if setup == "live":

                def drain():
                    while not stop.is_set():
                        try:
                            ws.recv(timeout=0.1)
                        except TimeoutError:
                            pass

                reader = threading.Thread(target=drain, daemon=True)
                reader.start()
            time.sleep(0.2)
        times = np.empty(CALLS, dtype=np.int64)
        for k in range(1, WARM + CALLS + 1):
            start = time.perf_counter_ns()
            _update(sink, k, t0)
            if k > WARM:
                times[k - WARM - 1] = time.perf_counter_ns() - start
        return times
    finally:
        stop.set()
        if reader is not None:
            reader.join()
        sink.close()
        if ws is not None:
            ws.__exit__(None, None, None)


def main() -> int:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for setup in ("mcap", "live", "stalled"):
            runs = [run_once(setup, Path(d)) for _ in range(RUNS)]
            p50 = np.median([np.percentile(r, 50) for r in runs]) / 1e3
            p99 = np.median([np.percentile(r, 99) for r in runs]) / 1e3
            worst = max(r.max() for r in runs) / 1e3
            rows.append((setup, p50, p99, worst))
            print(f"{setup:8s} p50 {p50:7.1f} us  p99 {p99:7.1f} us  max {worst:8.1f} us")
    lines = [
        "# SceneSink: time per update (observation + 10-step prediction with ellipses, 1 car)",
        "",
        f"`.venv/bin/python experiments/foxglove/sink_timing.py` on {platform.processor() or ''}"
        f" {platform.machine()}, Python {platform.python_version()}; {RUNS} runs of {CALLS}"
        f" calls each (after {WARM} untimed); p50 and p99: median over the runs; max: the"
        " slowest call of all runs. Load average (1 min) at the end: "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (a shared machine: the tails are"
        " mostly other processes' time slices).",
        "",
        "| setup | p50 [us] | p99 [us] | max [us] |",
        "| --- | --- | --- | --- |",
        *(f"| {s} | {a:.1f} | {b:.1f} | {c:.1f} |" for s, a, b, c in rows),
        "",
        "mcap: recording only; live: WebSocket server, one client reading everything; stalled:",
        "server plus recording, one subscribed client that never reads.",
        "",
    ]
    RESULTS.write_text("\n".join(lines))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
