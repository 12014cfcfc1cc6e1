"""`fpe`: the command-line front end, thin over the library.

Every command is a `cmd_<name>(args) -> int` function registered in `_build_parser`. Bad input
raises `InputError`; `main` prints it as one line on stderr and exits with status 2.
"""

from __future__ import annotations

import argparse
import errno
import gc
import math
import os
import queue
import signal
import sys
import threading
import time
from pathlib import Path

from fpe_jax import spec  # JAX-free, so `fpe --help` stays fast
from fpe_jax.errors import InputError
from fpe_jax.spec import ESTIMATORS, FIT_MODELS, FIT_NAMES, SOLVERS


def _add_log_flags(p: argparse.ArgumentParser) -> None:
    """Flags shared by every command that reads a drive log."""
    p.add_argument("--pose-topic", help="topic with the observed poses (default: the only one)")
    p.add_argument(
        "--truth-topic",
        help="ground-truth topic, e.g. the car's odometry (default: the only Odometry topic "
        "other than the pose topic, if there is one)",
    )
    p.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help="sample rate of a header-less x,y,z CSV (default: none; required for such a file)",
    )
    p.add_argument("--log-time", action="store_true", help="use recording time, not header.stamp")
    p.add_argument("--tf-parent", default="map", help="TF parent frame (default: map)")
    p.add_argument("--tf-child", default="other_base_link", help="TF child frame")
    p.add_argument(
        "--tag-id", type=int, metavar="N", help="AprilTag id on a detection topic (default: 0)"
    )
    p.add_argument(
        "--tag-to-base",
        metavar="X,Y,Z,YAW",
        help="the tag's mount on the leading car: centre [m] in its base frame, facing YAW [rad]; "
        "write --tag-to-base=-0.2,0,0.2,3.14 when X is negative (default: a tag -> base "
        "transform in the log)",
    )
    p.add_argument(
        "--drop-outside-tf",
        action="store_true",
        help="drop detections stamped outside the TF buffer (or in a gap longer than "
        "--max-tf-gap) instead of failing",
    )
    p.add_argument(
        "--max-tf-gap",
        type=float,
        metavar="S",
        help="longest gap [s] between two transforms of a TF edge that a lookup interpolates "
        "across (default per edge: max(4 x its median period, 0.2 s))",
    )


def _add_predictor_flags(p: argparse.ArgumentParser, *, required: bool) -> None:
    """--waypoints and exactly one of --preset / --config (optional: the 'default' preset)."""
    p.add_argument("--waypoints", required=True, help="waypoint / centerline / raceline file")
    src = p.add_mutually_exclusive_group(required=required)
    src.add_argument(
        "--preset", help="a built-in preset (see `fpe presets`; default: 'default' unless --config)"
    )
    src.add_argument(
        "--config", help="a tuned config JSON written by `fpe fit` (default: none, a preset)"
    )
    _add_settings_flags(p, "with --preset")


# flag -> Settings field of the car and the prediction grid (fpe_jax.spec.USER_SETTINGS)
SETTINGS_FLAGS = {
    "--wheelbase": "wheelbase_m",
    "--max-steer": "max_steer_rad",
    "--dt": "dt_s",
    "--horizon": "horizon",
}


def _add_settings_flags(p: argparse.ArgumentParser, when: str) -> None:
    g = p.add_argument_group(f"car and prediction settings ({when}; default: the preset's)")
    g.add_argument(
        "--wheelbase", type=float, metavar="M", help="wheelbase [m] (default: 0.325, F1TENTH)"
    )
    g.add_argument(
        "--max-steer",
        type=float,
        metavar="RAD",
        help="steering limit [rad] (default: 0.4189; seed presets 0.5236)",
    )
    g.add_argument("--dt", type=float, metavar="S", help="prediction step [s] (default: 0.1)")
    g.add_argument("--horizon", type=int, metavar="N", help="number of steps (default: 10)")


def _add_adapt_flags(p: argparse.ArgumentParser, save: bool) -> None:
    """--adapt, --delay and --calibrate-ellipses; with save, --save-state (of `fpe predict`)."""
    p.add_argument(
        "--adapt",
        action="store_true",
        help="learn the car's line and speed profile while predicting, lap by lap (from "
        "--config, or without one from the waypoints alone)",
    )
    p.add_argument(
        "--delay",
        type=float,
        metavar="S",
        help="with --adapt and no --config: your sensor's detection delay [s] (default: 0)",
    )
    if save:
        p.add_argument(
            "--save-state",
            metavar="OUT.json",
            help="with --adapt: write what it learned as a config (default: none)",
        )
    p.add_argument(
        "--calibrate-ellipses",
        action="store_true",
        help="with --adapt and a --config with ellipses: size them on the runner's own "
        "errors as it goes; "
        + (
            "writes each prediction's covariance, and --save-state saves them"
            if save
            else 'each reply carries its covariance "cov_m2" (H x 2 x 2, m^2)'
        )
        + " (default: off)",
    )


def _settings_from_args(args) -> dict:
    """{flag: (Settings field, value)} of the settings flags given (None where omitted)."""
    return {f: (k, getattr(args, f[2:].replace("-", "_"))) for f, k in SETTINGS_FLAGS.items()}


def _add_run_flags(p: argparse.ArgumentParser, off_track: bool = False) -> None:
    """Flags of every command that compiles with JAX; with off_track, --allow-off-track of those
    that check a drive against its waypoints."""
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="do not read or write the compilation cache (also FPE_NO_CACHE=1; see `fpe cache`)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    if off_track:
        p.add_argument(
            "--allow-off-track",
            action="store_true",
            help="use waypoints that the drive does not follow (off them, or run the other way)",
        )


def _progress(args):
    from fpe_jax.progress import Progress

    return Progress(quiet=getattr(args, "quiet", False))


def _predictor_options(args) -> dict:
    """The pipeline's predictor arguments of `_add_predictor_flags`."""
    return dict(preset=args.preset, config=args.config, settings=_settings_from_args(args))


def _log_options(args) -> dict:
    """The `_add_log_flags` values that both reading and describing a log take."""
    return dict(
        pose_topic=args.pose_topic,
        truth_topic=args.truth_topic,
        rate_hz=args.rate,
        tf_parent=args.tf_parent,
        tf_child=args.tf_child,
        tag_id=args.tag_id,
        tag_to_base=args.tag_to_base,
    )


def _drive_options(args) -> dict:
    """`io.load_drive`'s options from the `_add_log_flags` values."""
    return _log_options(args) | dict(
        log_time=args.log_time,
        drop_outside_tf=args.drop_outside_tf,
        max_tf_gap_s=args.max_tf_gap,
    )


def _run_options(args, say) -> dict:
    """The pipeline's options of `_add_run_flags`, with progress shown by `say`."""
    opts = dict(cache=not getattr(args, "no_cache", False), progress=say, warn=_warn)
    if hasattr(args, "allow_off_track"):
        opts["allow_off_track"] = args.allow_off_track
    return opts


def _warn(msg: str) -> None:
    """How the pipeline's warnings reach the user: one line on stderr, `--quiet` or not."""
    print(f"fpe: {msg}", file=sys.stderr)


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help that keeps the example's layout and says every option's default: an option whose
    help does not is marked "(required)", "(default: off)" for a switch, or "(default: VALUE)"."""

    def _get_help_string(self, action):
        text = action.help or ""
        if not action.option_strings or "default" in text or action.default == argparse.SUPPRESS:
            return text
        if action.required:
            return f"{text} (required)"
        if isinstance(action, argparse._StoreTrueAction):
            return f"{text} (default: off)"
        if action.default is None:
            return text
        return f"{text} (default: {action.default})"


class _Skipped(argparse.ArgumentParser):
    """The subparser of a command that `_build_parser(only=...)` leaves out: takes its arguments
    and groups and keeps nothing (none of ArgumentParser's own set-up is done)."""

    def __init__(self) -> None:
        pass

    def add_argument(self, *args, **kwargs) -> None:
        pass

    def add_argument_group(self, *args, **kwargs) -> _Skipped:
        return self

    def add_mutually_exclusive_group(self, *args, **kwargs) -> _Skipped:
        return self

    def set_defaults(self, **kwargs) -> None:
        pass


def _build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or with `only` (the first word of a command line) of that
    command alone: parsing its line needs no other (a command's start then skips adding the other
    commands' arguments and importing the node package for its own). A word that names no
    command gets the whole parser, which says so."""
    from fpe_jax import __version__  # the package root imports nothing eagerly

    parser = argparse.ArgumentParser(
        prog="fpe",
        description="Near-future pose prediction for race cars, fitted to your drives.",
        epilog="example:\n  fpe demo",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, help: str, example: str) -> argparse.ArgumentParser:
        """The subparser of `fpe NAME`, which runs `cmd_NAME`; its help ends with `example`."""
        if only is not None and name != only:
            return _Skipped()
        p = sub.add_parser(
            name,
            help=help,
            description=help,
            epilog=f"example:\n  {example}",
            formatter_class=_HelpFormatter,
        )
        p.set_defaults(func=globals()[f"cmd_{name}"])
        return p

    p = command(
        "predict",
        "predict every observation of a drive log",
        "fpe predict drive.mcap --waypoints track.csv --config tuned.json --out pred.csv",
    )
    p.add_argument("log", help="observations: CSV (t,x,y[,yaw][,v]), .mcap, rosbag2 folder, .bag")
    _add_predictor_flags(p, required=False)
    p.add_argument("--out", required=True, help="PRED.csv or PRED.mcap")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    _add_adapt_flags(p, save=True)
    _add_log_flags(p)
    _add_run_flags(p, off_track=True)

    p = command(
        "fit",
        "learn the car's line and fit the predictor to drives; report held-out metrics",
        "fpe fit lap1.mcap lap2.mcap --waypoints track.csv --out tuned.json",
    )
    p.add_argument("logs", nargs="+", metavar="LOG", help="drive logs, or one recipe .toml")
    p.add_argument(
        "--waypoints", help="waypoint / centerline / raceline file (default: the recipe's)"
    )
    p.add_argument("--out", help="CONFIG.json to write (default: the recipe's out)")
    p.add_argument(
        "--holdout", type=float, help="held-out fraction at each drive's end (default: 0.3)"
    )
    p.add_argument(
        "--test", nargs="+", metavar="LOG", help="separate held-out drives instead (default: none)"
    )
    p.add_argument(
        "--model",
        choices=FIT_MODELS,
        help="line (default): the car's own line and speed profile, learned from the drives; "
        "blend: linear / pure-pursuit blend; auto: line or blend, whichever predicts an inner "
        "validation split of the training data better",
    )
    p.add_argument(
        "--fit",
        help=f"comma list of {','.join(FIT_NAMES)} (default: the model's own: line "
        "delay,tau,smoothing,filter; filter only with the kalman estimator)",
    )
    p.add_argument(
        "--estimator",
        choices=ESTIMATORS,
        help="the line model's state estimator: kalman (default; a Kalman filter in the track "
        "frame) or theil-sen (robust lines through the recent observations)",
    )
    p.add_argument(
        "--blend", choices=("auto", "position", "heading"), help="blend mode (default: auto)"
    )
    _add_settings_flags(p, "saved in the config; a recipe may set them in [settings]")
    p.add_argument(
        "--solver",
        choices=SOLVERS,
        help="optimistix solver: bfgs on the robust loss (default) or lm on the residuals",
    )
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument(
        "--block-rows",
        type=int,
        metavar="N",
        help="target rows per block of the loss: memory vs. one more rollout (default: 8192)",
    )
    g = p.add_argument_group(
        "several processes (one per host or socket; start each with the same logs and options)"
    )
    g.add_argument(
        "--num-processes", type=int, metavar="N", help="processes in the fit (default: 1)"
    )
    g.add_argument(
        "--process-id",
        type=int,
        metavar="I",
        help="this process, 0 to N-1; process 0 writes and reports (default: 0 when N is 1)",
    )
    g.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="process 0's host and a free port there (default: $JAX_COORDINATOR_ADDRESS)",
    )
    g.add_argument(
        "--coordinator-timeout",
        type=float,
        metavar="S",
        help="seconds to wait for every process to join (default: 120)",
    )
    _add_log_flags(p)
    _add_run_flags(p, off_track=True)

    p = command(
        "evaluate",
        "metrics of a config or preset on a drive log",
        "fpe evaluate test.mcap --waypoints track.csv --config tuned.json",
    )
    p.add_argument("log", help="drive log (any supported format)")
    _add_predictor_flags(p, required=True)
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")
    _add_log_flags(p)
    _add_run_flags(p, off_track=True)

    p = command(
        "cache", "the compilation cache: its path, size and entries; clear it", "fpe cache info"
    )
    p.add_argument("action", choices=("info", "clear"), help="info: path, size; clear: empty it")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")

    command("presets", "list the built-in presets", "fpe presets")

    p = command(
        "info",
        "topics, rates, TF tree, pose/truth topics of a log; a waypoint file's path",
        "fpe info drive.mcap --waypoints track.csv",
    )
    p.add_argument(
        "log", nargs="?", help="drive log: .mcap, rosbag2 folder, .bag or CSV (or --waypoints)"
    )
    p.add_argument(
        "--waypoints",
        help="describe this waypoint file too: loop or open, length, what cleaning removed "
        "(default: none)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_log_flags(p)

    p = command(
        "simulate",
        "simulate a leading car's drive and its detections",
        "fpe simulate --track hairpin --duration 120 --out sim/",
    )
    p.add_argument(
        "--track",
        default="oval",
        help="oval | hairpin | random:SEED | a centerline/waypoint file (default: oval)",
    )
    p.add_argument(
        "--raceline",
        help="raceline file (with speeds) the driver follows (default: none, the centerline)",
    )
    p.add_argument(
        "--duration", type=float, default=60.0, metavar="S", help="length of the drive [s]"
    )
    p.add_argument("--latency", type=float, default=0.3, metavar="S", help="detection latency")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument(
        "--half-width",
        type=float,
        metavar="M",
        help="track half-width [m] (default: the built-in track's, else 1.1)",
    )
    p.add_argument("--stops-per-min", type=float, default=0.0, help="mean stops per minute")
    p.add_argument(
        "--sensor",
        choices=("map", "apriltag"),
        default="map",
        help="map: map-frame detections on /opp/pose (default); apriltag: the thesis' "
        "recording (camera-frame tag detections, the trailing car's TF, field-of-view dropouts)",
    )
    p.add_argument("--out", required=True, help="folder for drive.mcap, waypoints.csv, scenario")
    p.add_argument("--force", action="store_true", help="write into an existing non-empty folder")

    p = command(
        "convert",
        "write a drive log's observed poses as CSV t,x,y,yaw",
        "fpe convert drive.mcap --out drive.csv",
    )
    p.add_argument("log", help="drive log: .mcap, rosbag2 folder, .bag or CSV")
    p.add_argument("--out", required=True, help="DRIVE.csv (what `fpe run` reads on stdin)")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    _add_log_flags(p)

    p = command(
        "batch",
        "predict many cars at once (chunked, compiled once)",
        "fpe batch cars.csv --waypoints track.csv --config tuned.json --out poses.npy",
    )
    p.add_argument("states", help="cars: CSV with header x,y,yaw,v[,yaw_rate], or .npy (N, 4|5)")
    _add_predictor_flags(p, required=True)
    p.add_argument("--out", required=True, help="OUT.npy (N, H, 3) or OUT.csv")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--chunk", type=int, default=1 << 14, metavar="N", help="cars per call")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    _add_run_flags(p)

    p = command(
        "export",
        "export a tuned config for the car: JSON, ROS 2, StableHLO",
        "fpe export tuned.json --format all --out car/",
    )
    p.add_argument("config", help="a tuned config JSON written by `fpe fit`")
    p.add_argument(
        "--format",
        required=True,
        choices=("json", "ros2", "stablehlo", "all"),
        help="all: a folder with config.json, params.yaml, predictor.stablehlo (+ .json)",
    )
    p.add_argument("--out", required=True, help="output file (a folder for --format all)")
    p.add_argument("--node", default="future_pose_estimator", help="ROS 2 node name")
    p.add_argument(
        "--waypoints",
        help="waypoint file: baked into stablehlo, named in ros2 (default: the config's "
        "provenance, the file it was fitted on, checked by its hash)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing files")

    p = command(
        "run",
        "stream predictions: observations on stdin, JSON lines out",
        "fpe run --config tuned.json --waypoints track.csv < drive.csv",
    )
    p.add_argument("--config", help="a tuned config JSON (default: none; required without --adapt)")
    p.add_argument("--waypoints", required=True, help="waypoint / centerline / raceline file")
    p.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help="stamps from the rate (line k at k/HZ s): the original's header-less x,y,z poses "
        "(default: none, stamps from each line)",
    )
    _add_adapt_flags(p, save=False)
    p.add_argument(
        "--allow-off-track",
        action="store_true",
        help="warn, not fail, when the first observations are off the waypoints",
    )

    if only in (None, "node"):
        from fpe_jax.node import _cli as node_cli  # JAX-free

        node_cli.add_parser(
            sub,
            formatter_class=_HelpFormatter,
            epilog="example:\n  fpe node --ros1 --config car/config.json --waypoints car/track.csv",
        )

    p = command(
        "demo",
        "simulate, fit, compare with every preset, plot and export",
        "fpe demo --out out/demo",
    )
    p.add_argument("--out", default="out/demo", help="folder for plots and config (out/demo)")
    _add_run_flags(p)
    p.add_argument("--force", action="store_true", help="replace the demo's files in --out")

    p = command(
        "plot",
        "draw a drive with its 1 s predictions (trajectory overlay)",
        "fpe plot drive.mcap --waypoints track.csv --config tuned.json --out drive.png",
    )
    p.add_argument("log", help="drive log (any supported format)")
    _add_predictor_flags(p, required=True)
    p.add_argument("--out", required=True, help="FIG.png (or .pdf, .svg)")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    _add_log_flags(p)
    _add_run_flags(p, off_track=True)

    p = command(
        "view",
        "predict a drive log and show it in Foxglove (live WebSocket or MCAP)",
        "fpe view drive.mcap --waypoints track.csv --config tuned.json --foxglove",
    )
    p.add_argument("log", help="observations: CSV (t,x,y[,yaw][,v]), .mcap, rosbag2 folder, .bag")
    _add_predictor_flags(p, required=False)
    if only in (None, "view"):
        from fpe_jax.node import _view  # JAX-free

        _view.add_arguments(p)
    _add_log_flags(p)
    _add_run_flags(p, off_track=True)
    if only is not None and only not in sub.choices:
        return _build_parser()
    return parser


def cmd_export(args) -> int:
    from fpe_jax.io.export import export_config, provenance_waypoints

    waypoints = args.waypoints
    if waypoints is None:
        waypoints = provenance_waypoints(args.config)
        if waypoints is not None:
            print(f"waypoints from the config's provenance: {waypoints}", file=sys.stderr)
    opts = dict(node=args.node, waypoints=waypoints, force=args.force)
    written = export_config(args.config, args.format, args.out, **opts)
    for path in written:
        print(f"wrote {path}", file=sys.stderr)
    return 0


def cmd_run(args) -> int:
    # NumPy only: this command must work on a car without JAX
    # (tests/compile/test_executables.py checks it)
    from fpe_jax.runner._runner import Runner, run_stream

    rate_hz = None if args.rate is None else spec.check_rate(args.rate, "--rate", "value")
    if sys.stdin is None:
        raise InputError("stdin", "is closed", "observation lines on stdin")
    if sys.stdout is None:  # started with stdout closed: fail before the work, as a write would
        raise OSError(errno.EBADF, os.strerror(errno.EBADF))
    if args.calibrate_ellipses and (not args.adapt or args.config is None):
        why = "given without --adapt" if not args.adapt else "given without a config with ellipses"
        raise InputError("--calibrate-ellipses", why, "--adapt --config TUNED.json ...")
    if args.adapt:
        from fpe_jax.runner._adapt import AdaptiveRunner

        runner = AdaptiveRunner.from_files(
            args.config, args.waypoints, delay_s=args.delay, calibrate=args.calibrate_ellipses
        )
    elif args.config is None:
        raise InputError("--config", "missing", "a tuned config JSON (or --adapt)")
    else:
        runner = Runner.from_config(args.config, args.waypoints)
    runner.allow_off_track = args.allow_off_track
    return run_stream(runner, iter(sys.stdin.readline, ""), sys.stdout, sys.stderr, rate_hz)


def cmd_fit(args) -> int:
    from fpe_jax import pipeline

    with _progress(args) as say:
        res = pipeline.fit_logs(
            args.logs,
            args.waypoints,
            out=args.out,
            test=args.test,
            holdout=args.holdout,
            fit=args.fit,
            model=args.model,
            estimator=args.estimator,
            blend=args.blend,
            solver=args.solver,
            settings=_settings_from_args(args),
            force=args.force,
            log_options=_drive_options(args),
            block_rows=args.block_rows,
            coordinator=args.coordinator,
            num_processes=args.num_processes,
            process_id=args.process_id,
            coordinator_timeout_s=args.coordinator_timeout,
            **_run_options(args, say),
        )
    if not res.primary:  # process 0 of a multi-process fit reports
        return 0
    from fpe_jax.fit._report import format_fitted, format_table

    result = res.result
    print(format_fitted(result))
    print("\nheld-out:\n" + format_table(result.report))
    print("\n" + _coverage_line(result.report["fitted"]))
    print(f"wrote {res.out}")
    return 0


def cmd_evaluate(args) -> int:
    import json

    from fpe_jax import pipeline

    with _progress(args) as say:
        res = pipeline.evaluate_log(
            args.log,
            args.waypoints,
            **_predictor_options(args),
            log_options=_drive_options(args),
            **_run_options(args, say),
        )
    from fpe_jax.fit._report import format_table

    metrics = res.metrics
    name = args.config or args.preset
    if args.json:  # strict JSON: a metric without a value is null, never NaN
        print(json.dumps(_finite_or_null(metrics), indent=2, allow_nan=False))
    else:
        print(format_table({name: metrics}))
        if res.predictor.uncertainty is not None:
            print(_coverage_line(metrics))
    return 0


def _coverage_line(metrics: dict) -> str:
    return (
        f"ellipse coverage: 1-sigma {metrics['coverage_1sigma']:.1%} (ideal 39.3 %), "
        f"2-sigma {metrics['coverage_2sigma']:.1%} (ideal 86.5 %)"
    )


def cmd_cache(args) -> int:
    import json

    from fpe_jax.compile import _cache as cache  # JAX-free

    summary = cache.clear() if args.action == "clear" else cache.info()
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    verb = "removed" if args.action == "clear" else "holds"
    mb = summary["bytes"] / 1e6
    print(f"{summary['path']}: {verb} {summary['entries']} entries, {mb:.1f} MB")
    for name, sub in summary["subfolders"].items():
        print(f"  {name:60s} {sub['entries']:6d} entries {sub['bytes'] / 1e6:8.1f} MB")
    if cache.disabled():
        print("(off in this shell: FPE_NO_CACHE is set)")
    return 0


def _finite_or_null(v):
    """A JSON-ready copy of nested dicts/lists with every NaN or infinity replaced by None."""
    if isinstance(v, dict):
        return {k: _finite_or_null(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_finite_or_null(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def cmd_presets(args) -> int:
    from fpe_jax.io.config import PRESET_DOCS  # JAX-free

    for name, doc in PRESET_DOCS.items():
        print(f"{name:22s} {doc}")
    return 0


def cmd_predict(args) -> int:
    from fpe_jax import pipeline

    if args.adapt or args.save_state or args.delay is not None or args.calibrate_ellipses:
        return _predict_adaptive(args)
    with _progress(args) as say:
        res = pipeline.predict_log(
            args.log,
            args.waypoints,
            **_predictor_options(args),
            out=args.out,
            force=args.force,
            log_options=_drive_options(args),
            **_run_options(args, say),
        )
    n, h = res.poses_m.shape[:2]
    print(f"wrote {n} predictions x {h} steps to {args.out}", file=sys.stderr)
    return 0


def _predict_adaptive(args) -> int:
    """`fpe predict --adapt`: the learning runner over the drive in stream order (no JAX)."""
    from fpe_jax import pipeline

    if not args.adapt:
        flag = "--save-state" if args.save_state else "--delay"
        flag = "--calibrate-ellipses" if args.calibrate_ellipses else flag
        raise InputError(flag, "given without --adapt", f"--adapt {flag} ...")
    if args.preset:
        raise InputError("--preset", "given with --adapt", "--config, or neither")
    res = pipeline.predict_log_adaptive(
        args.log,
        args.waypoints,
        config=args.config,
        settings=_settings_from_args(args),
        delay_s=args.delay,
        out=args.out,
        save_state=args.save_state,
        calibrate=args.calibrate_ellipses,
        force=args.force,
        log_options=_drive_options(args),
        allow_off_track=args.allow_off_track,
        warn=_warn,
    )
    n, h = res.poses_m.shape[:2]
    print(f"wrote {n} predictions x {h} steps to {args.out}", file=sys.stderr)
    if args.save_state:
        print(f"wrote {args.save_state} ({res.runner.laps} laps learned)", file=sys.stderr)
    return 0


def _index_ranges(idx: list[int]) -> str:
    """[3, 4, 5, 9] -> '3-5, 9'."""
    runs: list[list[int]] = []
    for i in idx:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)


def cmd_info(args) -> int:
    import json

    from fpe_jax import pipeline

    info = pipeline.describe(args.log, args.waypoints, _log_options(args))
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    if args.log is not None:
        print(f"{info['source']}  ({info['format']}, {info['duration_s']:.3f} s)")
        for t in info["topics"]:
            rate = f"{t['rate_hz']:8.2f} Hz" if t["rate_hz"] is not None else "        - Hz"
            print(f"  {t['name']:32s} {t['type']:40s} {t['count']:8d} msgs {rate}")
        _print_tf(info)
        if info["pose_topic"] or "pose_error" in info:
            print(f"pose:  {info['pose_topic'] or '(none: ' + info['pose_error'] + ')'}")
            print(f"truth: {info['truth_topic'] or '(none)'}")
    if args.waypoints is not None:
        w = info["waypoints"]
        near, back = w["removed"]["near_duplicate_idx"], w["removed"]["backtracking_idx"]
        print(f"{w['source']}  ({w['format']}, {w['n_waypoints']} waypoints)")
        kind = "closed loop" if w["closed"] else "open path"
        print(
            f"  path: {kind}, {w['length_m']:.3f} m, {w['n_points']} points every {w['ds_m']:.4f} m"
        )
        where = (
            f": {'index' if len(back) == 1 else 'indices'} {_index_ranges(back)}" if back else ""
        )
        print(
            f"  removed: {len(near)} within {w['min_step_m']:g} m of the previous kept waypoint, "
            f"{len(back)} back-tracking{where} (0-based)"
        )
    return 0


def _print_tf(info: dict) -> None:
    """The TF tree and each detection topic's chain, as `fpe info` shows them."""
    if info.get("tf_tree") or info.get("tf_error"):
        print("TF tree:" + (f" ({info['tf_error']})" if info.get("tf_error") else ""))
    for e in info.get("tf_tree", []):
        indent = "  " * (e["depth"] + 1)
        link = f"{indent}{e['parent']} -> {e['child']}"
        if e["static"]:
            print(f"{link:48s} static")
        else:
            rate = f"{e['rate_hz']:8.2f} Hz" if e["rate_hz"] is not None else "        - Hz"
            span = f"[{e['first_s']:.3f}, {e['last_s']:.3f}] s"
            print(f"{link:48s} dynamic {e['count']:8d} transforms {rate}  {span}")
    for d in info.get("detections", []):
        print(f"detections {d['name']} (tag {d['tag_id']}):", end="")
        if "error" in d:
            print(f" cannot be composed: {d['error']}")
            continue
        n, empty = d["n_arrays"], d["n_empty_arrays"]
        print(f" {d['n_tag_detections']} of {n} arrays ({empty} empty)")
        print("  chain: " + " -> ".join(d["chain"]))
        for link in d["links"]:
            print(f"    {link['link']:40s} {link['from']}")


def cmd_convert(args) -> int:
    from fpe_jax import pipeline

    drive = pipeline.convert_log(
        args.log, args.out, force=args.force, log_options=_drive_options(args), warn=_warn
    )
    print(f"wrote {len(drive.t_s)} poses to {args.out}", file=sys.stderr)
    return 0


def cmd_simulate(args) -> int:
    from fpe_jax import pipeline

    res = pipeline.simulate_to(
        args.out,
        args.track,
        duration_s=args.duration,
        latency_s=args.latency,
        seed=args.seed,
        raceline=args.raceline,
        half_width_m=args.half_width,
        stops_per_min=args.stops_per_min,
        sensor=args.sensor,
        force=args.force,
    )
    d = res.drive
    print(
        f"wrote {len(d.t_s)} detections, {len(d.truth_t_s)} truth poses "
        f"({args.duration:g} s on {res.scenario['track']}) to {Path(args.out)}/",
        file=sys.stderr,
    )
    return 0


def cmd_batch(args) -> int:
    from fpe_jax import pipeline

    with _progress(args) as say:
        res = pipeline.predict_cars(
            args.states,
            args.waypoints,
            **_predictor_options(args),
            out=args.out,
            dtype=args.dtype,
            chunk=args.chunk,
            force=args.force,
            on_chunk=lambda done, n: say.count("predicting cars", done, n),
            **_run_options(args, say),
        )
    n, h = res.shape[:2]
    print(
        f"wrote {n} cars x {h} steps to {Path(args.out)} "
        f"({args.dtype}, {res.wall_s:.2f} s incl. compilation)",
        file=sys.stderr,
    )
    return 0


def cmd_demo(args) -> int:
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is not a folder", "a folder for the demo's plots and config")
    with _progress(args) as say:
        from fpe_jax import pipeline

        pipeline.start_jax(say, cache=not args.no_cache)
        from fpe_jax.demo import run_demo
        from fpe_jax.fit._report import format_fitted, format_table

        res = run_demo(out, progress=say, force=args.force)
    case, result = res.case, res.result
    p = result.params.physical()
    print(f"demo: {case.description}")
    print(format_fitted(result))
    print("\nheld-out (the separate test drive; seed = the 2019 node as written):")
    print(format_table(result.report))
    print(
        f"\nfitted delay {p['delay_s']:.3f} s vs true latency {case.latency_s:.3f} s "
        f"(error {p['delay_s'] - case.latency_s:+.3f} s)"
    )
    print("\nchecks:")
    for claim, ok, detail in res.checks:
        print(f"  {'PASS' if ok else 'FAIL'}  {claim}: {detail}")
    names = " ".join(f.name for f in res.files)
    print(f"\nwrote {out}/: {names}")
    print(f"demo finished in {res.seconds:.0f} s")
    return 0 if all(ok for _, ok, _ in res.checks) else 1


def cmd_plot(args) -> int:
    from fpe_jax import pipeline

    with _progress(args) as say:
        res = pipeline.plot_log(
            args.log,
            args.waypoints,
            args.out,
            **_predictor_options(args),
            force=args.force,
            log_options=_drive_options(args),
            **_run_options(args, say),
        )
    m = res.metrics
    print(
        f"wrote {res.out}: {m['n_predictions']} predictions, ADE {m['ade_m']:.3f} m, "
        f"FDE {m['fde_m']:.3f} m",
        file=sys.stderr,
    )
    return 0


def cmd_view(args) -> int:
    from fpe_jax import pipeline
    from fpe_jax.node import _view

    _view.check_args(args)  # before the slow part
    with _progress(args) as say:
        res = pipeline.predict_log(
            args.log,
            args.waypoints,
            **_predictor_options(args),
            log_options=_drive_options(args),
            **_run_options(args, say),
        )
    return _view.show(args, _view.predicted(res))


def _one_line(msg: str) -> str:
    """The message with control characters (a newline in a file name) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in msg)


def _sigterm(signum, frame):
    # SystemExit unwinds like Ctrl-C does, so atomic writers remove their temporary files
    raise SystemExit(128 + signum)


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot fail again."""
    try:
        fd = sys.stdout.fileno() if sys.stdout is not None else 1
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
    except (OSError, ValueError, AttributeError):  # stdout not a file (a test's capture)
        pass


_UNRAISABLE: queue.SimpleQueue = queue.SimpleQueue()  # `main`'s sys.unraisablehook is its put
_RESENDER: list = []  # the one thread that takes them (`_resend_interrupts`)


def _resend_interrupts() -> None:
    """The thread behind `main`'s sys.unraisablehook, `_UNRAISABLE.put`: a C method, so no
    second Ctrl-C can land inside the hook. A Ctrl-C (or SIGTERM) that landed in a callback
    Python cannot raise from (JAX's garbage-collection callback) is sent to the main thread
    again, a moment later (at once it could land in the same callback), so the work still stops;
    several in one burst are sent once; anything else is reported as usual. It is sent as a
    signal, so a main thread blocked in a system call (`fpe run` waiting on stdin) wakes."""
    kinds = ((SystemExit, signal.SIGTERM), (KeyboardInterrupt, signal.SIGINT))
    while True:
        burst = [_UNRAISABLE.get()]
        time.sleep(0.01)
        while not _UNRAISABLE.empty():
            burst.append(_UNRAISABLE.get())
        signums = []
        for unraisable in burst:
            sent = [n for kind, n in kinds if issubclass(unraisable.exc_type, kind)]
            if sent:
                signums += sent
            else:
                sys.__unraisablehook__(unraisable)
        if signums:
            # SIGTERM (15) over SIGINT (2)
            signal.pthread_kill(threading.main_thread().ident, max(signums))


# the library arguments that commands set from flags: the library's errors name the argument
LIBRARY_FLAGS = {
    "free": "--fit",
    "model": "--model",
    "solver": "--solver",
    "holdout": "--holdout",
    "preset": "--preset",
    "chunk": "--chunk",
    "dtype": "--dtype",
    "fmt": "--format",
    "node": "--node",
    "waypoints": "--waypoints",
    "half-width": "--half-width",
    "max_gap_s": "--max-tf-gap",
    "block_rows": "--block-rows",
    "coordinator": "--coordinator",
    "num_processes": "--num-processes",
    "process_id": "--process-id",
    "coordinator_timeout_s": "--coordinator-timeout",
}


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    args = _build_parser(words[0] if words else None).parse_args(argv)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _sigterm) if main_thread else None
    previous_hook = sys.unraisablehook
    previous_int = signal.getsignal(signal.SIGINT) if main_thread else None
    if main_thread:
        if not _RESENDER:
            _RESENDER.append(threading.Thread(target=_resend_interrupts, daemon=True))
            _RESENDER[0].start()
        sys.unraisablehook = _UNRAISABLE.put
    try:
        if getattr(args, "out", None) == "":  # Path("") is the current folder
            raise InputError("--out", "is empty", "a file or folder name")
        rc = args.func(args)
        if sys.stdout is not None:  # None when started with stdout closed
            sys.stdout.flush()  # here, not at exit: a closed pipe or a full disk is reported below
        return rc
    except InputError as e:
        if e.source in LIBRARY_FLAGS:  # the library names its argument, the CLI its flag
            e = InputError(LIBRARY_FLAGS[e.source], e.problem, e.expected)
        print(f"fpe: error: {_one_line(str(e))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        _ignore_interrupts(main_thread)
        print("fpe: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        if e.errno == errno.EPIPE:  # the reader went away (`fpe ... | head`): stop quietly
            _quiet_stdout()
            return 1
        if e.errno in (errno.ENOSPC, errno.EBADF, errno.EIO):  # stdout full or closed
            _quiet_stdout()
            print(f"fpe: error: cannot write the output ({e.strerror})", file=sys.stderr)
            return 1
        if e.filename is not None:  # a path the user gave that the system refuses
            print(f"fpe: error: {_one_line(str(e.filename))}: {e.strerror}", file=sys.stderr)
            return 2
        raise
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
            sys.unraisablehook = previous_hook
            if previous_int is not None:
                signal.signal(signal.SIGINT, previous_int)


def _ignore_interrupts(main_thread: bool) -> None:
    """After the first Ctrl-C has unwound the command, further ones are ignored while `main`
    reports it and returns (raised there they would end in a traceback)."""
    if main_thread:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


GC_YOUNG_THRESHOLD = 50_000  # objects allocated (net) between the collector's young passes
# commands that answer a stream for as long as it lasts: the interpreter's frequent, short
# passes keep their per-update pauses short
STREAM_COMMANDS = ("run", "node")


def entry() -> None:
    """The `fpe` console script: `main`, then the process ends without Python's teardown (the
    destructors of JAX's runtime and of the loaded executables, a pause after every command).
    Every file a command writes is closed when it returns; the streams are flushed here. A
    Ctrl-C that lands while `main` is already finishing ends the process quietly with 130."""
    # Importing JAX, equinox and matplotlib makes a great many objects that live until the
    # process ends; the collector's young passes every 700 new objects, and the full passes they
    # lead to, scanned them again and again and freed nothing (experiments/benchmarks/results.md,
    # History). Passes every 50,000 new objects still bound what cyclic garbage can hold.
    if not set(sys.argv[1:2]) & set(STREAM_COMMANDS):  # the first word names the command
        gc.set_threshold(GC_YOUNG_THRESHOLD, *gc.get_threshold()[1:])
    try:
        rc = main()
    except KeyboardInterrupt:
        rc = 130
    while True:  # nothing is left to interrupt; `main` has put back the handler that raises
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            break
        except KeyboardInterrupt:  # one landed before the line took effect
            rc = 130
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except OSError:  # the reader went away; nothing more can be said
            pass
    os._exit(rc)


if __name__ == "__main__":
    entry()
