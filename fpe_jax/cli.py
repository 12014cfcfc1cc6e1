"""`fpe`: the command-line front end, thin over the library.

Every command is a `cmd_<name>(args) -> int` function registered in `_build_parser`. Bad input
raises `InputError`; `main` prints it as one line on stderr and exits with status 2.
"""

from __future__ import annotations

import argparse
import sys

from fpe_jax.errors import InputError


def _add_log_flags(p: argparse.ArgumentParser) -> None:
    """Flags shared by every command that reads a drive log."""
    p.add_argument("--pose-topic", help="topic with the observed poses (default: the only one)")
    p.add_argument("--truth-topic", help="optional ground-truth topic (e.g. the car's odometry)")
    p.add_argument(
        "--rate", type=float, metavar="HZ", help="sample rate of a header-less x,y,z CSV"
    )
    p.add_argument("--log-time", action="store_true", help="use recording time, not header.stamp")
    p.add_argument("--tf-parent", default="map", help="TF parent frame (default: map)")
    p.add_argument("--tf-child", default="other_base_link", help="TF child frame")


def _load_drive_from_args(args):
    from fpe_jax import io

    return io.load_drive(
        args.log,
        pose_topic=args.pose_topic,
        truth_topic=args.truth_topic,
        rate_hz=args.rate,
        log_time=args.log_time,
        tf_parent=args.tf_parent,
        tf_child=args.tf_child,
    )


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fpe", description="Near-future pose prediction for race cars, fitted to your drives."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("predict", help="predict every observation of a drive log")
    p.add_argument("log", help="observations: CSV (t,x,y[,yaw][,v]), .mcap, rosbag2 folder, .bag")
    p.add_argument("--waypoints", required=True, help="waypoint / centerline / raceline file")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--preset", help="a built-in preset (see `fpe presets`)")
    src.add_argument("--config", help="a tuned config JSON written by `fpe fit`")
    p.add_argument("--out", required=True, help="PRED.csv or PRED.mcap")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    _add_log_flags(p)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("presets", help="list the built-in presets")
    p.set_defaults(func=cmd_presets)
    return parser


def cmd_presets(args) -> int:
    from fpe_jax.params import PRESET_DOCS

    for name, doc in PRESET_DOCS.items():
        print(f"{name:22s} {doc}")
    return 0


def cmd_predict(args) -> int:
    from fpe_jax import io
    from fpe_jax.config import load_params
    from fpe_jax.predict import predict_drive
    from fpe_jax.track import Track

    io.check_output_path(args.out, args.force)
    params = load_params(preset=args.preset, config=args.config)
    waypoints = io.load_waypoints(args.waypoints)
    drive = _load_drive_from_args(args)
    track = Track.from_waypoints(waypoints.xy_m)
    stamps_s, poses = predict_drive(params, drive, track)
    io.write_predictions(
        args.out, stamps_s, poses, params.settings.dt_s, drive=drive, force=args.force
    )
    print(
        f"wrote {len(stamps_s)} predictions x {poses.shape[1]} steps to {args.out}", file=sys.stderr
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as e:
        print(f"fpe: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
