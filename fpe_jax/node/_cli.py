"""`fpe node`: the live prediction node on ROS 1 (rospy) or ROS 2 (DDS). JAX-free."""

from __future__ import annotations

import argparse
import gc
import math
import signal
import sys
import threading

from fpe_jax.errors import InputError

INPUT_FLAGS = {"pose": "--pose-topic", "tags": "--tag-topic", "obstacles": "--obstacles-topic"}
INPUT_DEFAULTS = {
    "pose": "/opp/pose",
    "tags": "/tag_detections",
    "obstacles": "/perception/obstacles",
}
OUTPUT_FLAGS = {
    "markers": "markers",
    "path": "path",
    "covariance": "covariance",
    "obstacles": "obstacles-out",
    "trajectory": "trajectory",
}


def add_parser(subparsers, **kw) -> argparse.ArgumentParser:
    """Register `fpe node` (`run` is its `func`); `kw` go to `add_parser` (formatter, epilog)."""
    from fpe_jax.node._types import OUTPUTS

    p = subparsers.add_parser(
        "node",
        help="run the live prediction node on ROS 1 or ROS 2",
        description="Subscribe to the opponent's observations, publish its predicted poses. "
        "Flags win over private ROS 1 parameters (~config, ~waypoints, ~pose_topic, ...).",
        **kw,
    )
    mw = p.add_mutually_exclusive_group(required=True)
    mw.add_argument("--ros1", action="store_true", help="ROS 1 through rospy (Debian packages)")
    mw.add_argument("--ros2", action="store_true", help="ROS 2 over DDS (the cyclonedds wheel)")
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--config",
        help="a tuned config JSON written by `fpe fit` / `fpe export` (default: none; one of "
        "--config, --preset, --params-file or the ~config parameter)",
    )
    src.add_argument("--preset", help="a built-in preset (see `fpe presets`; default: none)")
    src.add_argument(
        "--params-file",
        metavar="YAML",
        help="the ROS 2 parameter file `fpe export --format ros2` writes (config and waypoints; "
        "default: none)",
    )
    p.add_argument(
        "--waypoints",
        help="waypoint / centerline / raceline file (map frame; default: the ~waypoints "
        "parameter, or the --params-file's)",
    )
    p.add_argument(
        "--adapt",
        action="store_true",
        help="learn each opponent's line and pace during the race (from --config, or from the "
        "waypoints and the shape prior alone; default: off)",
    )
    p.add_argument(
        "--delay",
        type=float,
        metavar="S",
        help="with --adapt and no config: your sensor's detection delay [s] (default: 0)",
    )
    p.add_argument(
        "--calibrate-ellipses",
        action="store_true",
        help="with --adapt and a config with ellipses: size each opponent's on its own errors "
        "as it goes (default: off)",
    )
    g = p.add_argument_group("input (one of; default: the AprilTag detections)")
    g.add_argument(
        "--pose-topic", metavar="T", help="PoseStamped or Odometry in the map frame (default: none)"
    )
    g.add_argument(
        "--tag-topic",
        metavar="T",
        help="apriltag_ros AprilTagDetectionArray (default: /tag_detections)",
    )
    g.add_argument(
        "--obstacles-topic",
        metavar="T",
        help="f110_msgs/ObstacleArray, e.g. /perception/obstacles (default: none)",
    )
    g.add_argument("--tag-id", type=int, default=0, metavar="N", help="AprilTag id (default 0)")
    g.add_argument(
        "--tag-to-base",
        metavar="X,Y,Z,YAW",
        help="the tag's mount on the leading car (default: a tag -> base transform on /tf_static)",
    )
    g.add_argument("--map-frame", "--tf-parent", dest="map_frame", default="map", help="map frame")
    g.add_argument(
        "--tf-child", default="other_base_link", help="the leading car's base frame (tags)"
    )
    g.add_argument(
        "--drop-after",
        type=float,
        default=1.0,
        metavar="S",
        help="drop an obstacle track after S seconds without updates",
    )
    g.add_argument(
        "--tf-wait",
        type=float,
        default=0.5,
        metavar="S",
        help="how long a detection waits for the TF at its stamp before it is dropped",
    )
    g.add_argument("--max-tracks", type=int, default=16, metavar="N", help="most obstacles tracked")
    o = p.add_argument_group("outputs (each can be renamed or switched off)")
    for name, flag in OUTPUT_FLAGS.items():
        o.add_argument(
            f"--{flag}-topic", metavar="T", help=f"{OUTPUTS[name][1]} (default {OUTPUTS[name][0]})"
        )
        o.add_argument(f"--no-{flag}", action="store_true", help=f"do not publish {name}")
    o.add_argument(
        "--markers-every",
        type=float,
        default=0.1,
        metavar="S",
        help="each opponent's markers at most every S seconds, one opponent's per message (0.1)",
    )
    o.add_argument(
        "--trajectory-every",
        type=float,
        default=1.0,
        metavar="S",
        help="look at the OpponentTrajectory every S seconds (1.0): sent when the line changed "
        "or a subscriber joined since the last one sent",
    )
    p.add_argument("--node-name", default="future_pose_estimator", help="ROS node name")
    p.add_argument("--domain-id", type=int, help="ROS 2 domain id (default: ROS_DOMAIN_ID or 0)")
    p.add_argument(
        "--foxglove",
        nargs="?",
        type=int,
        const=8765,
        metavar="PORT",
        help="serve the live scene to Foxglove on 127.0.0.1:PORT (default: off; PORT 8765)",
    )
    p.add_argument(
        "--record", metavar="X.mcap", help="record the Foxglove scene to MCAP (default: none)"
    )
    p.add_argument(
        "--stats",
        metavar="FILE.json",
        help="at exit, write the own update time of every observation [ns] (benchmarks; "
        "default: none)",
    )
    p.set_defaults(func=run)
    return p


def _transport(args):
    if args.ros1:
        from fpe_jax.node._ros1 import Ros1Transport

        return Ros1Transport(args.node_name)
    try:
        from fpe_jax.node._dds import DdsTransport
    except ImportError as e:
        raise InputError(
            "--ros2", f"the ROS 2 (DDS) transport is not available ({e})", "--ros1"
        ) from None
    import os

    from fpe_jax.node._types import typestore

    domain = (
        args.domain_id if args.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID", 0))
    )
    return DdsTransport(typestore("ros2"), domain_id=domain, node_name=args.node_name)


def _param(transport, args, flag_value, name, default=None):
    """A flag's value, else the transport's private parameter (ROS 1), else the default."""
    if flag_value is not None:
        return flag_value
    get = getattr(transport, "param", None)
    return get(name, default) if get is not None else default


def _preset_config(name: str) -> dict:
    """A built-in preset as a config dict (builds it with JAX: on a car without JAX, export a
    config where JAX runs and give --config)."""
    from fpe_jax.io.config import params_to_config
    from fpe_jax.model._params import presets

    if name not in presets:
        raise InputError("--preset", f"unknown preset {name!r}", f"one of {', '.join(presets)}")
    return params_to_config(presets[name])


# flag -> (lowest, highest, lowest excluded): a node setting outside these is a typing slip
_RANGES = {
    "--drop-after": (0.0, 3600.0, True),
    "--tf-wait": (0.0, 60.0, False),
    "--max-tracks": (1, 256, False),
    "--tag-id": (0, 2**31 - 1, False),
    "--markers-every": (0.0, 3600.0, False),
    "--trajectory-every": (0.0, 3600.0, False),
}


def options_from_args(args, transport):
    """(config dict, waypoints (K, 2), NodeOptions) from the flags and the ROS parameters.
    Raises InputError for a missing or mismatched config / waypoint file."""
    from fpe_jax.io.config import check_waypoints, read_config
    from fpe_jax.node._core import NodeOptions
    from fpe_jax.node._types import OUTPUTS
    from fpe_jax.runner._runner import load_waypoints_xy

    config = _param(transport, args, args.config, "config")
    waypoints = _param(transport, args, args.waypoints, "waypoints")
    if args.params_file is not None:
        from fpe_jax.io.export import read_ros2_params

        cfg, wp_file = read_ros2_params(args.params_file)
        waypoints = waypoints or wp_file
        config = args.params_file
    elif args.preset is not None:
        cfg = _preset_config(args.preset)
    elif config is not None:
        cfg = read_config(config)
    elif args.adapt:
        cfg = None  # learned from the waypoints and the shape prior alone
    else:
        raise InputError("fpe node", "no config given", "--config, --preset or --params-file")
    if args.delay is not None and (not args.adapt or cfg is not None):
        raise InputError("--delay", "given with a config or without --adapt", "--adapt --delay S")
    if args.calibrate_ellipses and (not args.adapt or cfg is None or not cfg.get("uncertainty")):
        raise InputError(
            "--calibrate-ellipses",
            "given without --adapt or a config with ellipses",
            "--adapt --config TUNED.json --calibrate-ellipses",
        )
    if not waypoints:
        raise InputError("fpe node", "no waypoints given", "--waypoints FILE (or ~waypoints)")
    xy = load_waypoints_xy(waypoints)
    if cfg is not None:
        check_waypoints(cfg, config or args.preset, xy, waypoints)
    given = [k for k, f in INPUT_FLAGS.items() if getattr(args, f[2:].replace("-", "_"))]
    if len(given) > 1:
        raise InputError("fpe node", f"several inputs ({', '.join(given)})", "one input topic")
    kind = given[0] if given else _param(transport, args, None, "input", "tags")
    topic = getattr(args, INPUT_FLAGS[kind][2:].replace("-", "_")) if given else None
    topic = topic or _param(transport, args, None, f"{kind}_topic", INPUT_DEFAULTS[kind])
    outputs = {}
    for name, flag in OUTPUT_FLAGS.items():
        if getattr(args, f"no_{flag.replace('-', '_')}"):
            outputs[name] = None
        else:
            value = getattr(args, f"{flag.replace('-', '_')}_topic")
            key = f"{flag.replace('-', '_')}_topic"
            outputs[name] = _param(transport, args, value, key, OUTPUTS[name][0])
    for flag, (lo, hi, open_lo) in _RANGES.items():
        value = getattr(args, flag[2:].replace("-", "_"))
        if not (math.isfinite(value) and (lo < value if open_lo else lo <= value) and value <= hi):
            side = "(" if open_lo else "["
            raise InputError("fpe node", f"{flag} {value}", f"a number in {side}{lo}, {hi}]")
    opts = NodeOptions(
        input=kind,
        topic=topic,
        map_frame=args.map_frame,
        tag_id=args.tag_id,
        tag_to_base=args.tag_to_base,
        car_frame=args.tf_child,
        drop_after_s=args.drop_after,
        tf_wait_s=args.tf_wait,
        max_tracks=args.max_tracks,
        outputs=outputs,
        adapt=args.adapt,
        delay_s=args.delay,
        calibrate=args.calibrate_ellipses,
        markers_every_s=args.markers_every,
        trajectory_every_s=args.trajectory_every,
    )
    return cfg, xy, opts


def run(args) -> int:
    from pathlib import Path

    from fpe_jax.node._core import Node

    for flag in ("config", "waypoints", "params_file"):  # before connecting to any middleware
        value = getattr(args, flag)
        if value is not None and not Path(value).is_file():
            raise InputError(value, "does not exist", f"--{flag.replace('_', '-')} FILE")
    transport = _transport(args)
    stop = threading.Event()
    scene = None
    try:
        cfg, xy, opts = options_from_args(args, transport)
        if args.foxglove is not None or args.record:
            from fpe_jax.node._foxglove import SceneSink

            scene = SceneSink(port=args.foxglove, mcap_path=args.record, frame_id=opts.map_frame)
        node = Node(transport, cfg, xy, opts, scene=scene)
        node.start()
        # what start-up built (type stores, message classes, the runners' tables) lives as long
        # as the node: kept out of the collector's full passes, which would otherwise pause the
        # callbacks for milliseconds
        gc.freeze()
        print(
            f"fpe node: {transport.flavour}, {opts.input} on {opts.topic}, publishing "
            + ", ".join(f"{k} {v}" for k, v in opts.outputs.items() if v),
            file=sys.stderr,
            flush=True,
        )

        def end(signum, frame):
            stop.set()

        previous = {s: signal.signal(s, end) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            transport.spin(stop)
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
    finally:
        transport.close()
        if scene is not None:
            scene.close()
    if args.stats:
        import json

        from fpe_jax.io.writers import write_text

        stats = {"update_ns": node.update_ns, "n_published": node.n_published}
        write_text(args.stats, json.dumps(stats) + "\n", force=True)
    print(f"fpe node: stopped after {node.n_published} predictions", file=sys.stderr)
    return 0
