"""`fpe view LOG --config CONFIG --waypoints FILE [--foxglove [PORT]] [--out X.mcap]`: predict a
drive log offline, as `fpe predict` does, and show it in Foxglove.

With --foxglove the scene (`fpe_jax.node.SceneSink`) is served over Foxglove's WebSocket
protocol and replayed on the log's clock (`--speed` times as fast; `--loop` repeats it until
Ctrl-C); with --out it is recorded to a new MCAP file (the first pass of a replay; written
as fast as it can be when --foxglove is not given). The replay speed is `--speed`, since
`--rate` is the log flag that `fpe predict` has (a header-less CSV's sample rate).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from fpe_jax.errors import InputError

CAR_ID = "opp"  # the one car of a drive log (as in /opp/pose)
DEFAULT_PORT = 8765  # Foxglove's default WebSocket port


def add_arguments(p) -> None:
    """`fpe view`'s own flags (the CLI adds the predictor, log and run flags of `fpe predict`)."""
    p.add_argument(
        "--foxglove",
        type=int,
        nargs="?",
        const=DEFAULT_PORT,
        metavar="PORT",
        help=f"serve Foxglove's WebSocket protocol on PORT (default {DEFAULT_PORT}; 0 picks a "
        "free one) and replay the drive on its own clock",
    )
    p.add_argument(
        "--foxglove-host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)"
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="FACTOR",
        help="replay FACTOR times as fast as recorded",
    )
    p.add_argument("--loop", action="store_true", help="replay again and again until Ctrl-C")
    p.add_argument(
        "--out", help="record the scene to X.mcap (Foxglove protobuf schemas; default: none)"
    )
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--map-frame", default="map", help="frame_id of every message (default map)")


def check_args(args) -> None:
    """InputError for `fpe view` flags that cannot work, before anything slow runs."""
    from fpe_jax import io

    if args.foxglove is None and args.out is None:
        raise InputError("fpe view", "nothing to do", "--foxglove [PORT] and/or --out X.mcap")
    if args.out is not None:
        io.check_output_path(args.out, args.force, (args.log, args.waypoints, args.config))
        if Path(args.out).suffix.lower() != ".mcap":
            raise InputError(args.out, "unknown output format", ".mcap")
    if args.foxglove is not None and not 0 <= args.foxglove <= 65535:
        raise InputError("--foxglove", f"port {args.foxglove} out of range", "0 to 65535")
    if not (np.isfinite(args.speed) and args.speed > 0):
        raise InputError("--speed", f"{args.speed} is not a positive number", "e.g. 1 or 4")


@dataclasses.dataclass(frozen=True)
class Predicted:
    """A drive's predictions in the map frame.

    Attributes:
        stamps_ns: (N,) int64 observation stamps [ns].
        xy_m: (N, 2) observed positions [m]; yaw_rad: (N,) observed headings [rad] (NaN: none).
        poses: (N, H, 3) predicted x [m], y [m], yaw [rad] at step_stamps_ns.
        step_stamps_ns: (N, H) int64 time each step predicts [ns].
        cov_xy_m2: (N, H, 2, 2) map-frame covariance [m^2]; NaN without the config's uncertainty.
        track_xy_m: (K, 2) the waypoints [m]; track_closed: whether they form a loop.
        valid: (N,) bool, whether each prediction had enough history (an invalid one is drawn
            grey, without path or ellipses, as in `fpe predict --out X.mcap`).
    """

    stamps_ns: np.ndarray
    xy_m: np.ndarray
    yaw_rad: np.ndarray
    poses: np.ndarray
    step_stamps_ns: np.ndarray
    cov_xy_m2: np.ndarray
    track_xy_m: np.ndarray
    track_closed: bool
    valid: np.ndarray


def predicted(res) -> Predicted:
    """The scene's view of `fpe_jax.pipeline.predict_log`'s result (`Predictions`)."""
    from fpe_jax.io import ros_msgs as rm

    drive = res.drive
    poses = np.asarray(res.poses_m, dtype=np.float64)
    n, h, _ = poses.shape
    cov = np.full((n, h, 2, 2), np.nan) if res.cov_m2 is None else np.asarray(res.cov_m2)
    if res.valid is None:
        raise ValueError("fpe view: the predictions carry no validity (predict_log sets it)")
    stamps_ns = rm.seconds_to_ns(np.asarray(res.stamps_s, dtype=np.float64))
    return Predicted(
        stamps_ns=stamps_ns,
        xy_m=np.asarray(drive.xy_m, dtype=np.float64),
        yaw_rad=np.asarray(drive.yaw_rad, dtype=np.float64),
        poses=poses,
        step_stamps_ns=stamps_ns[:, None] + rm.seconds_to_ns(np.arange(1, h + 1) * res.dt_s),
        cov_xy_m2=cov,
        track_xy_m=np.asarray(res.predictor.waypoints_xy_m, dtype=np.float64),
        track_closed=bool(res.track_closed),
        valid=np.asarray(res.valid, dtype=bool),
    )


def feed(sinks, pred: Predicted, *, speed: float | None = None, offset_ns: int = 0) -> None:
    """Send the drive to each of `sinks` (SceneSinks): the track, then each observation and its
    prediction, stamps moved by `offset_ns`; with `speed`, paced on the log's clock (speed times
    as fast), else as fast as they take them."""
    for sink in sinks:
        sink.track(pred.track_xy_m, closed=pred.track_closed)
    start_wall = time.monotonic()
    t0_ns = int(pred.stamps_ns[0]) if len(pred.stamps_ns) else 0
    for k, stamp in enumerate(pred.stamps_ns.tolist()):
        if speed is not None:
            wait = start_wall + (stamp - t0_ns) * 1e-9 / speed - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        x, y = pred.xy_m[k]
        steps = pred.step_stamps_ns[k] + offset_ns
        for sink in sinks:
            sink.observation(CAR_ID, stamp + offset_ns, float(x), float(y), float(pred.yaw_rad[k]))
            sink.prediction(
                CAR_ID, stamp + offset_ns, pred.poses[k], pred.cov_xy_m2[k], steps,
                bool(pred.valid[k]),
            )  # fmt: skip


def show(args, pred: Predicted) -> int:
    """Serve (--foxglove) and/or record (--out) the predicted drive, as `check_args` allowed."""
    from fpe_jax import io
    from fpe_jax.node._foxglove import SceneSink

    live = None
    if args.foxglove is not None:
        live = SceneSink(port=args.foxglove, host=args.foxglove_host, frame_id=args.map_frame)
    speed = args.speed if live is not None else None
    try:
        if live is not None:
            print(
                f"serving Foxglove on ws://{args.foxglove_host}:{live.port} "
                "(Foxglove: Open connection -> Foxglove WebSocket); Ctrl-C ends",
                file=sys.stderr,
            )
        record = io.atomic_output(args.out, args.force) if args.out else contextlib.nullcontext()
        with record as tmp:  # the recording holds the first pass; Ctrl-C leaves no file
            rec = SceneSink(mcap_path=tmp, frame_id=args.map_frame) if tmp else None
            try:
                feed([s for s in (live, rec) if s is not None], pred, speed=speed)
            finally:
                if rec is not None:
                    rec.close()
        # each pass continues the clock (a viewer's time never runs backwards)
        span_ns = (
            int(pred.step_stamps_ns.max() - pred.stamps_ns.min()) if len(pred.stamps_ns) else 0
        )
        passes = 1
        while args.loop and live is not None:
            feed([live], pred, speed=speed, offset_ns=passes * span_ns)
            passes += 1
    finally:
        if live is not None:
            live.close()
    n, h = pred.poses.shape[:2]
    done = ([f"served on port {live.port}"] if live is not None else []) + (
        [f"wrote {args.out}"] if args.out else []
    )
    print(f"{n} predictions x {h} steps: {' and '.join(done)}", file=sys.stderr)
    return 0
