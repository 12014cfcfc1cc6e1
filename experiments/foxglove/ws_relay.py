"""Let Foxglove Studio 1.x (or Lichtblick before its foxglove.sdk.v1 support) watch `fpe view` or
`fpe node --foxglove`: a WebSocket relay that renames the protocol.

foxglove-sdk's server speaks the Foxglove WebSocket protocol under the subprotocol name
`foxglove.sdk.v1` and refuses (HTTP 400) a client that asks only for the old name,
`foxglove.websocket.v1`, as those apps do. This relay accepts the old name on 127.0.0.1:LISTEN and
passes every frame unchanged, both ways, to the server at --to under the new one; the messages
are the same under both names.

    fpe view data/samples/drive.mcap --config fit/sim-oval.json \\
        --waypoints data/tracks/oval.csv --foxglove 8765 --loop &
    .venv/bin/python experiments/foxglove/ws_relay.py --listen 8766 --to ws://127.0.0.1:8765
    # then in the app: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8766

Needs the `websockets` package (in the project's `dev` extra). Ctrl-C ends it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys
import threading

SDK_SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk's server accepts
STUDIO_SUBPROTOCOL = "foxglove.websocket.v1"  # the same protocol's name in Studio 1.x


def start_relay(listen_port: int, upstream: str) -> threading.Event:
    """Serve ws://127.0.0.1:`listen_port` with subprotocol foxglove.websocket.v1 and pass every
    frame unchanged between each client and `upstream` (foxglove.sdk.v1), in a daemon thread;
    returns once listening, with an Event that stops it.

    Foxglove Studio 1.x and Lichtblick before its foxglove.sdk.v1 support ask only for the old
    name of the protocol, which foxglove-sdk's server refuses (HTTP 400); the messages are the
    same under both names.
    """
    import websockets

    stop_event = threading.Event()
    ready = threading.Event()

    async def pump(source, sink) -> None:
        with contextlib.suppress(websockets.ConnectionClosed):
            async for frame in source:
                await sink.send(frame)

    async def handle(client) -> None:
        async with websockets.connect(
            upstream, subprotocols=[SDK_SUBPROTOCOL], max_size=None, compression=None
        ) as server:
            tasks = [
                asyncio.create_task(pump(client, server)),
                asyncio.create_task(pump(server, client)),
            ]
            _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()

    async def run() -> None:
        async with websockets.serve(
            handle,
            "127.0.0.1",
            listen_port,
            subprotocols=[STUDIO_SUBPROTOCOL],
            max_size=None,
            compression=None,
        ):
            ready.set()
            while not stop_event.is_set():
                await asyncio.sleep(0.1)

    threading.Thread(target=lambda: asyncio.run(run()), daemon=True).start()
    if not ready.wait(timeout=10):
        raise SystemExit(f"the relay could not listen on 127.0.0.1:{listen_port}")
    return stop_event


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--listen", type=int, default=8766, help="port to serve on (127.0.0.1)")
    ap.add_argument("--to", default="ws://127.0.0.1:8765", help="the foxglove-sdk server")
    args = ap.parse_args()
    stop_event = start_relay(args.listen, args.to)
    print(
        f"relaying ws://127.0.0.1:{args.listen} ({STUDIO_SUBPROTOCOL}) to {args.to} "
        f"({SDK_SUBPROTOCOL}); Ctrl-C ends",
        file=sys.stderr,
    )
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        stop_event.set()
    return 0


if __name__ == "__main__":
    sys.exit(main())
