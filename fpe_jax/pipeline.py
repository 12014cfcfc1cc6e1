"""The pipelines every front end calls: a log (or arrays) in, results (and the files asked for)
out, nothing printed.

    from fpe_jax import pipeline
    res = pipeline.predict_log("drive.mcap", "waypoints.csv", config="tuned.json", out="p.csv")
    res.poses_m.shape  # (N, H, 3) map-frame x [m], y [m], yaw [rad]

Each function reads its inputs once, moves the drive and waypoints into their local frame
(`local_log`: epoch stamps and UTM-sized coordinates removed in float64 before float32 sees them),
checks that the drive follows the waypoints, runs the library, and returns a small result
object. `progress(msg)` is told each slow phase (the CLI shows it on stderr), `warn(msg)` what
the user should know about the result (detections dropped, cars off the track). JAX is imported on
first use, in float64 unless a function says otherwise, with the compilation cache unless
`cache=False` (`start_jax`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax import spec  # JAX-free
from fpe_jax.errors import InputError

Progress = Callable[[str], None]


def _silent(msg: str) -> None:
    pass


def start_jax(
    progress: Progress = _silent,
    *,
    x64: bool = True,
    cache: bool = True,
    executables=True,
    processes=None,
):
    """Import JAX (telling `progress`): float64 unless x64=False, the compilation cache unless
    cache=False (of whole executables, or with executables=False of JAX's XLA output:
    `cache.enable`), joined to the other processes of a `ProcessGroup` (`processes`,
    `fpe_jax.fit._processes.join`) before anything asks for a device. Returns the jax module."""
    progress("loading JAX")
    import jax

    if x64:
        jax.config.update("jax_enable_x64", True)
    if processes is not None:
        from fpe_jax.fit._processes import join

        progress(f"joining {processes.num_processes} processes at {processes.address}")
        join(processes)
    from fpe_jax.compile import _cache as exe_cache

    if not cache:
        exe_cache.disable()
    else:
        exe_cache.enable(executables)
    return jax


@dataclasses.dataclass(frozen=True)
class Predictor:
    """What a prediction runs with.

    Attributes:
        params: the predictor (`Params`).
        waypoints_xy_m: (K, 2) float64 waypoints [m] in the map frame.
        waypoints_source: the waypoint file (or "waypoints" for an array).
        config: the config dict read from `config`, or None for a preset.
        name: the preset's name or "config NAME.json".
    """

    params: Any
    waypoints_xy_m: np.ndarray
    waypoints_source: str
    config: dict | None
    name: str

    @property
    def uncertainty(self) -> dict | None:
        """The config's prediction uncertainty (None for a preset or a config without one)."""
        return None if self.config is None else self.config.get("uncertainty")


def load_waypoints_xy(waypoints) -> tuple[np.ndarray, str]:
    """((K, 2) float64 [m], source) of a waypoint file or of a (K, 2) array."""
    if isinstance(waypoints, str | Path):
        from fpe_jax import io

        return io.load_waypoints(waypoints).xy_m, str(waypoints)
    return np.asarray(waypoints, dtype=np.float64), "waypoints"


def load_predictor(
    waypoints, *, preset: str | None = None, config=None, settings: dict | None = None
) -> Predictor:
    """The predictor of a preset (default: "default") or a tuned config, reading the config once.

    waypoints: a waypoint file or (K, 2) array [m]; a line-model config is checked against them.
    settings: {flag or name: (Settings field, value)} for a preset (`spec.USER_SETTINGS`); None
    values are ignored; an error with a config (which carries its own).
    """
    from fpe_jax.io.config import load_params_and_config

    wp, source = load_waypoints_xy(waypoints)
    params, cfg = load_params_and_config(
        preset=preset, config=config, settings=settings, waypoints=(source, wp)
    )
    name = f"config {Path(config).name}" if config is not None else preset or "default"
    return Predictor(params, wp, source, cfg, name)


def load_log(log, log_options: dict | None = None, warn: Progress = _silent):
    """A `Drive` from a log path (`io.load_drive` with log_options; `warn` is told of the
    detections `drop_outside_tf` dropped), or the Drive given."""
    from fpe_jax.drive import Drive

    if isinstance(log, Drive):
        return log
    from fpe_jax import io

    drive = io.load_drive(log, **(log_options or {}))
    if note := io.dropped_note(drive):
        warn(note)
    return drive


def _paths(*given) -> tuple:
    """The file paths among a function's inputs (arrays and Drives are no files)."""
    return tuple(g for g in given if isinstance(g, str | Path))


@dataclasses.dataclass(frozen=True)
class LocalLog:
    """A drive and its track in their local frame (`drive.local_frame`).

    Attributes:
        drive: the drive, stamps from its first one [s], positions from `origin_xy_m` [m].
        waypoints_xy_m: (K, 2) the waypoints in the same frame [m].
        track: `Track` of those waypoints.
        t0_s: the subtracted time [s]; origin_xy_m: (2,) the subtracted position [m].
    """

    drive: Any
    waypoints_xy_m: np.ndarray
    track: Any
    t0_s: float
    origin_xy_m: np.ndarray


def local_log(
    drive, waypoints_xy_m, *, source: str, name: str, allow_off_track: bool = False
) -> LocalLog:
    """The drive and waypoints in their local frame, with the drive checked to follow the
    waypoints (`path.check_on_track`: InputError naming `source` and `name` unless
    allow_off_track). Needs JAX (the Track)."""
    from fpe_jax.drive import local_frame
    from fpe_jax.geometry._track import Track

    local, wp, t0_s, origin = local_frame(drive, waypoints_xy_m)
    track = Track.from_waypoints(wp)
    check_drive_on_track(local, track, source=source, name=name, allow=allow_off_track)
    return LocalLog(local, wp, track, t0_s, origin)


def check_drive_on_track(drive, track, *, source: str, name: str, allow: bool = False) -> None:
    """InputError unless the drive's observations follow the track's waypoints (see
    `fpe_jax.geometry.check_on_track`); both in the same frame."""
    from fpe_jax.geometry._path import check_on_track

    check_on_track(
        drive.xy_m,
        np.asarray(track.xy_m),
        np.asarray(track.heading_rad),
        source=source,
        drive=name,
        allow=allow,
    )


def _log_name(log, what: str = "the drive") -> str:
    """How errors name a log (or waypoints) given as a path or as data."""
    return str(log) if isinstance(log, str | Path) else what


def _check_out(out, force: bool, suffixes, expected: str, problem=None, inputs=()) -> Path | None:
    """Refuse a bad output path before the slow part (None when there is none), one of the
    `inputs` included whatever `force` says; `problem` (of the path) says what is wrong with its
    suffix."""
    if out is None:
        return None
    from fpe_jax import io

    path = io.check_output_path(out, force, _paths(*inputs))
    if path.suffix.lower() not in suffixes:
        raise InputError(out, (problem or (lambda p: "unknown output format"))(path), expected)
    return path


@dataclasses.dataclass(frozen=True)
class Predictions:
    """`predict_log`'s result.

    Attributes:
        stamps_s: (N,) the observations' stamps [s] (the log's own clock).
        poses_m: (N, H, 3) predicted x [m], y [m] (map frame), yaw [rad] at dt_s, 2 dt_s, ...
        cov_m2: (N, H, 2, 2) map-frame covariance [m^2] when the config has an uncertainty.
        dt_s: the prediction step [s].
        predictor: what predicted; drive: the drive as read (map frame).
        track_closed: whether the waypoints form a loop.
        valid: (N,) bool, whether each prediction had enough history (the CSV's `valid`).
    """

    stamps_s: np.ndarray
    poses_m: np.ndarray
    cov_m2: np.ndarray | None
    dt_s: float
    predictor: Predictor
    drive: Any
    track_closed: bool = False
    valid: np.ndarray | None = None


def predict_log(
    log,
    waypoints,
    *,
    preset: str | None = None,
    config=None,
    settings: dict | None = None,
    out=None,
    force: bool = False,
    log_options: dict | None = None,
    allow_off_track: bool = False,
    cache: bool = True,
    progress: Progress = _silent,
    warn: Progress = _silent,
) -> Predictions:
    """Predict from every observation of a drive log (`fpe predict`); with `out` (.csv or .mcap)
    also write them (`io.write_predictions`), refusing an existing file unless force."""
    _check_out(out, force, (".csv", ".mcap"), ".csv or .mcap", inputs=(log, waypoints, config))
    start_jax(progress, cache=cache)
    from fpe_jax.evaluate._evaluate import covariance_map, path_heading, prediction_covariance
    from fpe_jax.model._history import drive_valid
    from fpe_jax.predict._predict import predict_rows, states_from_drive

    progress("reading the drive and waypoints")
    pred = load_predictor(waypoints, preset=preset, config=config, settings=settings)
    drive = load_log(log, log_options, warn)
    loc = local_log(
        drive,
        pred.waypoints_xy_m,
        source=pred.waypoints_source,
        name=_log_name(log),
        allow_off_track=allow_off_track,
    )
    params = pred.params
    progress(f"predicting {len(drive.t_s)} observations")
    states = states_from_drive(params, loc.drive, loc.track)
    poses = predict_rows(params, states, loc.track)
    cov = None
    if pred.uncertainty is not None:  # the config's ellipses, turned into the map frame
        cov_track = prediction_covariance(params, states, loc.track, pred.uncertainty)
        cov = covariance_map(cov_track, path_heading(loc.track, poses.xy_m, states))
    stamps_s = loc.drive.t_s + loc.t0_s
    poses = np.array(poses.packed(), dtype=np.float64)  # a writable copy
    poses[..., :2] += loc.origin_xy_m
    dt_s = params.settings.dt_s
    closed = bool(loc.track.closed)
    valid = np.asarray(drive_valid(loc.drive, params.settings.history), dtype=bool)
    if out is not None:
        from fpe_jax import io

        progress(f"writing {out}")
        io.write_predictions(
            out,
            stamps_s,
            poses,
            dt_s,
            drive=drive,
            cov_m2=cov,
            valid=valid,
            track_xy_m=pred.waypoints_xy_m,
            track_closed=closed,
            force=force,
        )
    return Predictions(stamps_s, poses, cov, dt_s, pred, drive, closed, valid)


@dataclasses.dataclass(frozen=True)
class AdaptivePredictions:
    """`predict_log_adaptive`'s result.

    Attributes:
        stamps_s: (N,) the observations' stamps [s]; poses_m: (N, H, 3) predicted x [m], y [m]
        (map frame), yaw [rad]; dt_s: the prediction step [s].
        runner: the `adapt.AdaptiveRunner` after the drive (what it learned: `state_config`).
        drive: the drive as read.
        cov_m2: (N, H, 2, 2) map-frame covariance [m^2] of each prediction as calibrated then
            (with calibrate), else None.
    """

    stamps_s: np.ndarray
    poses_m: np.ndarray
    dt_s: float
    runner: Any
    drive: Any
    cov_m2: np.ndarray | None = None


def predict_log_adaptive(
    log,
    waypoints,
    *,
    config=None,
    settings: dict | None = None,
    delay_s: float | None = None,
    out=None,
    save_state=None,
    calibrate: bool = False,
    force: bool = False,
    log_options: dict | None = None,
    allow_off_track: bool = False,
    warn: Progress = _silent,
) -> AdaptivePredictions:
    """`fpe predict --adapt`: the learning runner (`adapt.AdaptiveRunner`, no JAX) over every
    observation of a drive log in stream order, starting from `config` or, without one, from the
    waypoints alone (with the sensor's `delay_s`). With `out` (.csv or .mcap) the predictions
    are written, with `save_state` what it learned, as a config. With `calibrate` the config's
    ellipses are calibrated on the runner's own errors as it goes (`AdaptiveRunner`'s
    calibrate): each prediction's covariance is written and saved with the state."""
    from fpe_jax import io
    from fpe_jax.geometry._path import build_path, check_on_track
    from fpe_jax.io.config import check_waypoints, read_config, write_config
    from fpe_jax.runner._adapt import predict_drive_adaptive

    inputs = (log, waypoints, config)
    _check_out(out, force, (".csv", ".mcap"), ".csv or .mcap", inputs=inputs)
    if save_state is not None:
        io.check_output_path(save_state, force, _paths(*inputs))
    wp, source = load_waypoints_xy(waypoints)
    cfg = None
    if config is not None:
        cfg = read_config(config)
        check_waypoints(cfg, config, wp, source)
    if calibrate and (cfg is None or cfg.get("uncertainty") is None):
        raise InputError(
            "--calibrate-ellipses", "given without a config with ellipses", "--config TUNED.json"
        )
    given = {k: v for k, v in (settings or {}).values() if v is not None}
    drive = load_log(log, log_options, warn)
    path = build_path(wp)
    xy, heading = (np.asarray(path[k]) for k in ("xy_m", "heading_rad"))
    check_on_track(
        drive.xy_m, xy, heading, source=source, drive=_log_name(log), allow=allow_off_track
    )
    kw = {"calibrate": True, "with_covariance": True} if calibrate else {}
    runner, poses, *cov = predict_drive_adaptive(
        drive, wp, cfg, settings=given or None, delay_s=delay_s, **kw
    )
    cov = cov[0] if cov else None
    if out is not None:
        io.write_predictions(
            out, drive.t_s, poses, runner.dt_s, drive=drive, cov_m2=cov, force=force
        )
    if save_state is not None:
        prov = {"drives": [_log_name(log)], "started_from": str(config or "waypoints")}
        write_config(save_state, runner.state_config(prov), force=force)
    return AdaptivePredictions(np.asarray(drive.t_s), poses, runner.dt_s, runner, drive, cov)


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """`evaluate_log`'s result: `metrics` (`evaluate.evaluate`; with the config's uncertainty,
    the ellipses' coverage too) of `predictor` on the drive."""

    metrics: dict
    predictor: Predictor


def evaluate_log(
    log,
    waypoints,
    *,
    preset: str | None = None,
    config=None,
    settings: dict | None = None,
    log_options: dict | None = None,
    allow_off_track: bool = False,
    cache: bool = True,
    progress: Progress = _silent,
    warn: Progress = _silent,
) -> Evaluation:
    """Metrics of a preset or config on a drive log (`fpe evaluate`)."""
    start_jax(progress, cache=cache)
    from fpe_jax.evaluate._evaluate import Dataset, evaluate, make_targets

    progress("reading the drive and waypoints")
    pred = load_predictor(waypoints, preset=preset, config=config, settings=settings)
    loc = local_log(
        load_log(log, log_options, warn),
        pred.waypoints_xy_m,
        source=pred.waypoints_source,
        name=_log_name(log),
        allow_off_track=allow_off_track,
    )
    data = Dataset(loc.drive, loc.track, make_targets(loc.drive, pred.params.settings))
    if len(data.targets.rows) == 0:
        raise InputError(_log_name(log), "no prediction has a target", "a longer drive")
    progress(f"predicting {len(data.targets.rows)} observations and scoring them")
    metrics = evaluate(pred.params, [data], uncertainty=pred.uncertainty)
    return Evaluation(metrics, pred)


@dataclasses.dataclass(frozen=True)
class PlotResult:
    """`plot_log`'s result: the figure's path and the metrics of the predictions drawn."""

    out: Path
    metrics: dict
    predictor: Predictor


def plot_log(
    log,
    waypoints,
    out,
    *,
    preset: str | None = None,
    config=None,
    settings: dict | None = None,
    force: bool = False,
    log_options: dict | None = None,
    allow_off_track: bool = False,
    cache: bool = True,
    progress: Progress = _silent,
    warn: Progress = _silent,
) -> PlotResult:
    """Draw a drive with one predictor's predictions, whole and zoomed where it misses most
    (`fpe plot`); predicts in the local frame, draws in the map frame."""
    from fpe_jax.plots import FIGURE_SUFFIXES

    figure = lambda p: f"unknown figure type {p.suffix!r}"
    inputs = (log, waypoints, config)
    path = _check_out(out, force, FIGURE_SUFFIXES, " or ".join(FIGURE_SUFFIXES), figure, inputs)
    start_jax(progress, cache=cache)
    from fpe_jax.evaluate._evaluate import heldout_predictions
    from fpe_jax.evaluate._metrics import errors_m, summarize
    from fpe_jax.plots import plot_drive

    progress("reading the drive and waypoints")
    pred = load_predictor(waypoints, preset=preset, config=config, settings=settings)
    drive = load_log(log, log_options, warn)
    source = _log_name(log)
    loc = local_log(
        drive,
        pred.waypoints_xy_m,
        source=pred.waypoints_source,
        name=source,
        allow_off_track=allow_off_track,
    )
    progress(f"predicting {len(drive.t_s)} observations")
    held = heldout_predictions(loc.drive, loc.track, {pred.name: pred.params})
    if len(held.rows) == 0:
        raise InputError(source, "no observation has a later one to compare with", "a longer drive")
    m = summarize(errors_m(held.pred_xy_m[pred.name], held.target_xy_m, held.mask))
    o = loc.origin_xy_m
    held = dataclasses.replace(  # back to the map frame the user knows
        held,
        origin_xy_m=held.origin_xy_m + o,
        target_xy_m=held.target_xy_m + o,
        pred_xy_m={k: v + o for k, v in held.pred_xy_m.items()},
    )
    progress(f"drawing {out}")
    plot_drive(drive, pred.waypoints_xy_m, held, pred.name, m, path, source=source)
    return PlotResult(path, m, pred)


@dataclasses.dataclass(frozen=True)
class CarPredictions:
    """`predict_cars`' result.

    Attributes:
        poses_m: (N, H, 3) x [m], y [m] (map frame), yaw [rad]: in memory, or with a `.npy`
            `out` a read-only memory map of the file written.
        shape: (N, H, 3).
        wall_s: wall time [s] of the prediction, compilation included, with the reading and
            writing of the cars it overlaps.
        predictor: the `Predictor`.
        off_track: (N,) bool: the cars far from the track (`batch.off_track_cars`), whose
            predictions mean nothing.
    """

    poses_m: np.ndarray
    shape: tuple[int, int, int]
    wall_s: float
    predictor: Predictor
    off_track: np.ndarray


def predict_cars(
    cars,
    waypoints,
    *,
    preset: str | None = None,
    config=None,
    settings: dict | None = None,
    out=None,
    dtype: str = "float32",
    chunk: int = 1 << 14,
    force: bool = False,
    cache: bool = True,
    progress: Progress = _silent,
    warn: Progress = _silent,
    on_chunk: Callable[[int, int], None] | None = None,
) -> CarPredictions:
    """Predict many cars at once (`fpe batch`), chunked, in `dtype`.

    cars: a CSV (header x,y,yaw,v[,yaw_rate]) or .npy path, or an (N, 4|5) array: x [m], y [m],
    yaw [rad], v [m/s][, yaw rate [rad/s]] in the map frame. out: optional .npy or .csv to write.
    on_chunk(done, n) is told after each chunk; `warn` of the cars far from the track.

    The cars stream through the predictor a chunk at a time: each chunk is read (a .npy in
    pieces, `io.CarFile`), moved to the local frame and judged on or off the track on the
    predictor's worker threads; with a .npy `out` its poses are moved back to the map frame and
    written by a writer thread (`io.PosesFile`) while later chunks run, so memory holds a few
    chunks whatever N. A CSV (in or out) is held whole: text is the slow path. The file is the
    one the whole array gives, byte for byte, written under a temporary name and renamed into
    place at the end.
    """
    import time

    from fpe_jax import io

    path = None
    if out is not None:
        path = io.check_output_path(out, force, _paths(cars, waypoints, config))
        if path.suffix.lower() not in (".npy", ".csv"):
            raise InputError(path, f"unknown output type {path.suffix!r}", "OUT.npy or OUT.csv")
    spec.check_chunk(chunk)
    # the predictor runs in `dtype` (batch.py pins it); its chunk function is a plain jit
    start_jax(progress, x64=False, cache=cache, executables=False)
    from fpe_jax.drive import map_origin
    from fpe_jax.geometry._path import on_track_m
    from fpe_jax.geometry._track import Track
    from fpe_jax.predict._batch import (
        BatchPredictor,
        CarBlocks,
        _check_cars,
        off_track_judge,
        off_track_summary,
        origin_dtype,
        with_origin,
    )

    progress("reading the cars and waypoints")
    pred = load_predictor(waypoints, preset=preset, config=config, settings=settings)
    wp = pred.waypoints_xy_m
    origin = map_origin(wp)  # removed in float64 before the (float32) computation
    track = Track.from_waypoints(wp - origin)
    source = _log_name(cars, "the cars")
    if isinstance(cars, str | Path):
        file = io.CarFile.open(cars)
        n, read_rows = file.n_cars, file.read
    else:
        given = _check_cars(cars)
        n = given.shape[0]
        read_rows = lambda a, b: np.array(given[a:b], dtype=np.float64)  # noqa: E731 (a copy)
    off = np.zeros(n, dtype=bool)
    judge = off_track_judge(pred.params, track)

    def read(a: int, b: int) -> np.ndarray:  # on the predictor's worker threads
        block = read_rows(a, b)
        block[:, :2] -= origin
        off[a:b] = judge(block[:, :2], n)
        return block

    h, dt_s = pred.params.settings.horizon, pred.params.settings.dt_s
    out_dtype = origin_dtype(dtype, origin)  # float64 where float32 cannot hold map coordinates
    predictor = BatchPredictor(pred.params, track, dtype=dtype, chunk=chunk)
    chunks = predictor.chunks(CarBlocks(n, read), progress=on_chunk)
    progress(f"predicting {n} cars")
    t0 = time.perf_counter()

    if path is None or path.suffix.lower() == ".csv":  # in memory (text is the slow path)
        poses = np.empty((n, h, 3), dtype=out_dtype)
        for rows, part in chunks:
            if isinstance(rows, slice):
                with_origin(part, origin, out=poses[rows])
            else:
                poses[rows] = with_origin(part, origin, out=np.empty(part.shape, out_dtype))
        if path is not None:
            progress(f"writing {out}")
            io.write_poses(path, poses, dt_s, force=force, off_track=off)
    else:
        buffer = np.empty((min(chunk, n), h, 3), dtype=out_dtype)  # reused: no fresh pages

        with io.PosesFile(path, n, h, out_dtype, dt_s, force=force) as f:

            def write(rows, part: np.ndarray) -> None:  # on the writer thread, one at a time
                moved = with_origin(part, origin, out=buffer[: part.shape[0]])
                if isinstance(rows, slice):
                    f.write(moved)
                else:
                    f.patch(rows, moved)

            _overlapped(write, chunks)
        poses = np.load(path, mmap_mode="r")
    wall_s = time.perf_counter() - t0
    if warning := off_track_summary(off, source, on_track_m(np.asarray(track.xy_m))):
        warn(warning)
    return CarPredictions(poses, (n, h, 3), wall_s, pred, off)


def _overlapped(consume: Callable[..., None], items, depth: int = 4) -> None:
    """consume(*item) for each item, in order, on a second thread while the next items are made
    (JAX and file writes release the GIL); at most `depth` items wait. The first error of either
    side is raised here, after the thread has stopped."""
    import queue
    import threading

    todo: queue.Queue = queue.Queue(depth)
    failed: list[BaseException] = []

    def drain() -> None:
        while (item := todo.get()) is not None:
            if not failed:  # after a failure, only empty the queue
                try:
                    consume(*item)
                except BaseException as e:  # noqa: BLE001 (raised on the calling thread)
                    failed.append(e)

    thread = threading.Thread(target=drain, name="fpe-writer", daemon=True)
    thread.start()
    try:
        for item in items:
            if failed:
                break
            todo.put(item)
    finally:
        getattr(items, "close", lambda: None)()  # a generator stopped early cleans up now
        todo.put(None)
        thread.join()
    if failed:
        raise failed[0]


@dataclasses.dataclass(frozen=True)
class FitOutcome:
    """`fit_logs`' result: the `FitResult`, the config written and where."""

    result: Any
    config: dict
    out: Path
    primary: bool = True  # False on processes 1 and on of a multi-process fit: nothing written


def _solver_option(name: str | None):
    """The solver `fit` gets for a --solver (or recipe) name: None for the default (bfgs), so a
    warm fit loads its stored solve without importing optimistix (~0.1-0.3 s, `fit._Static`)."""
    from fpe_jax.fit._recipe import solver_named

    name = name or spec.SOLVERS[0]
    return None if name == spec.SOLVERS[0] else solver_named(name, "--solver")


def _waypoint_provenance(path, entries) -> dict | None:
    """{"file": absolute path, "sha256": waypoints_sha256} of the waypoint file every drive of
    `entries` ((drive, waypoints, description)) ran on; None when there is none or they differ."""
    from fpe_jax.geometry._path import waypoints_sha256

    sha = {waypoints_sha256(wp) for _, wp, _ in entries}
    if path is None or len(sha) != 1:
        return None
    return {"file": str(Path(path).resolve()), "sha256": sha.pop()}


def _fit_inputs(logs, waypoints, test, out, flags: dict, log_options, progress, warn):
    """(drives, test drives, out, options) of `fit_logs`: entries (drive, waypoints, description)
    read from the logs (or the one recipe .toml they name), the options of the recipe (or the
    defaults) with the given `flags` on top, and under "inputs" the files read."""
    if len(logs) == 1 and str(logs[0]).endswith(".toml"):
        from fpe_jax.fit._recipe import load_recipe  # (and tomllib) only for a recipe

        r = load_recipe(logs[0])
        opts = dict(
            holdout=r.holdout,
            fit=r.fit,
            blend=r.blend,
            model=r.model,
            solver=r.solver,
            estimator=r.estimator,
            settings=r.settings,
            waypoints=r.waypoints,
        )
        return r.drives, r.test_drives, out or r.out, opts | flags | {"inputs": r.inputs}
    if waypoints is None:
        raise InputError("--waypoints", "missing", "a waypoint file for the drives")
    wp, _ = load_waypoints_xy(waypoints)

    def read(logs, what):
        entries = []
        for i, log in enumerate(logs, 1):
            progress(f"reading {what} {i}/{len(logs)}: {log}")
            entries.append((load_log(log, log_options, warn), wp, _log_name(log)))
        return entries

    drives, tests = read(logs, "drive"), read(test or [], "test drive")
    opts = dict(holdout=0.3, fit=None, blend="auto", model=None, solver=None, settings={})
    opts["estimator"] = None
    opts["inputs"] = _paths(*logs, *(test or []), waypoints)
    source = str(waypoints) if isinstance(waypoints, str | Path) else None
    return drives, tests, out, opts | {"waypoints": source} | flags


def fit_logs(
    logs,
    waypoints=None,
    *,
    out=None,
    test=None,
    holdout: float | None = None,
    fit: str | None = None,
    model: str | None = None,
    estimator: str | None = None,
    blend: str | None = None,
    solver: str | None = None,
    settings: dict | None = None,
    force: bool = False,
    log_options: dict | None = None,
    allow_off_track: bool = False,
    cache: bool = True,
    progress: Progress = _silent,
    warn: Progress = _silent,
    block_rows: int | None = None,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    coordinator_timeout_s: float | None = None,
) -> FitOutcome:
    """Fit the predictor to drive logs and write the tuned config (`fpe fit`).

    logs: drive logs (paths or Drives), or one recipe .toml (which names the drives, waypoints,
    options and perhaps `out`); waypoints: the drives' waypoint file or (K, 2) array. The other
    options override the recipe's (None: the recipe's, or the defaults); `settings` ({flag:
    (Settings field, value)}) go on top of the recipe's [settings]. block_rows: target rows per
    block of the fit's loss (`fit_params`). Returns the fit, the config and the path written.

    With num_processes > 1 this is one of that many processes started alike (same logs and
    options; `fpe_jax.fit._processes`): process_id 0 .. num_processes - 1, coordinator process
    0's HOST:PORT (default $JAX_COORDINATOR_ADDRESS), coordinator_timeout_s how long to wait
    for all of them. The row blocks of the loss are spread over every process's devices; every
    process ends with the same fit (checked); only process 0 reports progress and warnings and
    writes `out` (the others return primary=False). Call it before anything has run on JAX in
    this process.
    """
    from fpe_jax import io
    from fpe_jax.fit import _processes
    from fpe_jax.io.config import params_to_config, write_config

    group = _processes.process_group(coordinator, num_processes, process_id, coordinator_timeout_s)
    if group is not None and not group.primary:  # process 0 says it all, once
        progress = warn = _silent
    logs = list(logs)
    fit_names = None if fit is None else spec.check_fit_names(fit, "free", "value")
    if holdout is not None:
        spec.check_fraction(holdout, "holdout", "value")
    is_recipe = len(logs) == 1 and str(logs[0]).endswith(".toml")
    if out is None and not is_recipe:
        raise InputError("--out", "missing", "CONFIG.json to write")
    if out is not None:
        io.check_output_path(out, force, _paths(*logs, *(test or ()), waypoints))
    flags = dict(holdout=holdout, blend=blend, model=model, solver=solver, estimator=estimator)
    flags = {k: v for k, v in flags.items() if v is not None}
    progress("reading drives")
    read = (flags, log_options, progress, warn)
    drives, tests, out, opts = _fit_inputs(logs, waypoints, test, out, *read)
    drives, tests = _local_entries(drives), _local_entries(tests)
    if out is None:
        raise InputError("--out", "missing (neither flag nor recipe names it)", "CONFIG.json")
    out = io.check_output_path(out, force, _paths(*opts["inputs"]))
    jax = start_jax(progress, cache=cache, processes=group)
    from fpe_jax.fit._fit import fit as fit_drives
    from fpe_jax.fit._report import line_section, provenance
    from fpe_jax.geometry._track import Track
    from fpe_jax.io.config import apply_settings
    from fpe_jax.model._params import presets

    # the recipe's [settings], then the given settings on top
    init = apply_settings(presets["default"], opts["settings"], str(logs[0]))
    given = {k: v for k, v in (settings or {}).items() if v[1] is not None}
    init = apply_settings(init, given)

    tracks = [Track.from_waypoints(wp) for _, wp, _ in drives]
    test_tracks = [Track.from_waypoints(wp) for _, wp, _ in tests] or None
    wp_source = (
        f"{logs[0]}: the waypoints" if waypoints is None else _log_name(waypoints, "waypoints")
    )
    for (d, _, desc), tr in zip(drives + tests, tracks + (test_tracks or []), strict=True):
        check_drive_on_track(d, tr, source=wp_source, name=desc, allow=allow_off_track)
    try:
        result = fit_drives(
            [d for d, _, _ in drives],
            tracks,
            free=fit_names or opts["fit"] or None,
            model=opts["model"] or "line",
            blend=opts["blend"],
            holdout=opts["holdout"],
            test_drives=[d for d, _, _ in tests] or None,
            test_tracks=test_tracks,
            solver=_solver_option(opts["solver"]),
            estimator=opts["estimator"] or spec.LINE_ESTIMATOR,
            init=init,
            progress=progress,
            block_rows=block_rows,
            devices=1 if group is None else len(jax.devices()),
        )
    except Exception as e:
        lost = None if group is None else _processes.lost_process(group, e)
        if lost is None:
            raise
        raise lost from e
    meta = drives[0][0].meta
    topics = {"pose": meta.get("pose_topic"), "truth": meta.get("truth_topic")}
    sources = [desc for _, _, desc in drives] + [f"test:{desc}" for _, _, desc in tests]
    prov = provenance(result, sources, topics)
    wp_file = _waypoint_provenance(opts["waypoints"], drives + tests)
    if wp_file is not None:  # what `fpe export` uses when --waypoints is omitted
        prov["waypoints"] = wp_file
    line = line_section(result, None if wp_file is None else wp_file["file"])
    cfg = params_to_config(
        result.params, uncertainty=result.uncertainty, provenance=prov, line=line
    )
    if group is not None:  # the fitted values and the report, not the clock or the paths
        import json

        same = {k: cfg[k] for k in ("params", "settings", "uncertainty")}
        same |= {"heldout": result.report, "line": line and line["waypoints_sha256"]}
        _processes.check_same(group, json.dumps(same, sort_keys=True).encode())
    if group is None or group.primary:
        write_config(out, cfg, force=force)
    if group is not None:
        _processes.leave()
    return FitOutcome(result, cfg, out, primary=group is None or group.primary)


def _local_entries(entries):
    """(drive, waypoints, description) entries in their local frames (see drive.local_frame)."""
    from fpe_jax.drive import local_frame

    return [(*local_frame(d, wp)[:2], desc) for d, wp, desc in entries]


def convert_log(
    log, out, *, force: bool = False, log_options: dict | None = None, warn: Progress = _silent
):
    """Write a drive log's observed poses as CSV t,x,y,yaw (`fpe convert`); returns the Drive."""
    from fpe_jax import io

    _check_out(out, force, (".csv",), ".csv", inputs=(log,))
    drive = load_log(log, log_options, warn)
    io.write_drive_csv(out, drive, force=force)
    return drive


def describe_waypoints(path) -> dict:
    """JSON-ready summary of a waypoint file and of the path the predictors build from it."""
    from fpe_jax import io
    from fpe_jax.geometry._path import build_path

    wp = io.load_waypoints(path)
    p = build_path(wp.xy_m, source=str(path))
    return {
        "source": str(path),
        "format": wp.format,
        "n_waypoints": len(wp.xy_m),
        "closed": p["closed"],
        "length_m": p["length_m"],
        "n_points": len(p["xy_m"]),
        "ds_m": p["ds_m"],
        "min_step_m": p["min_step_m"],
        "removed": {
            "near_duplicate_idx": p["removed_close_idx"].tolist(),
            "backtracking_idx": p["removed_backtrack_idx"].tolist(),
        },
    }


def describe(log=None, waypoints=None, log_options: dict | None = None) -> dict:
    """`fpe info`'s summary: a log's topics, rates, TF tree and pose/truth topics
    (`io.describe_log`), and with `waypoints` that file's under "waypoints"."""
    from fpe_jax import io

    if log is None and waypoints is None:
        raise InputError("LOG", "missing", "a drive log, or --waypoints W to describe waypoints")
    info = {} if log is None else io.describe_log(log, **(log_options or {}))
    if waypoints is not None:
        info["waypoints"] = describe_waypoints(waypoints)
    return info


def simulate_to(
    out,
    track: str = "oval",
    *,
    duration_s: float = 60.0,
    latency_s: float = 0.3,
    seed: int = 0,
    raceline=None,
    half_width_m: float | None = None,
    stops_per_min: float = 0.0,
    sensor: str = "map",
    force: bool = False,
):
    """Simulate a leading car's drive and write drive.mcap, waypoints.csv and the scenario into
    the folder `out` (`fpe simulate`); returns `sim.simulate`'s result."""
    from fpe_jax import io
    from fpe_jax.sim import _sim as sim

    out = Path(out)
    spec.check_simulation(duration_s, latency_s, seed, stops_per_min, "simulate")
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file", "a folder to write the simulated drive into")
    if out.is_dir() and any(out.iterdir()) and not force:  # fail before simulating
        raise InputError(out, "exists and is not empty; pass --force to write into it")
    if not out.exists():
        io.check_output_path(out, False)  # its parent exists and is writable
    sim.check_simulation_out(out, (track, raceline))
    res = sim.simulate(
        track,
        duration_s=duration_s,
        latency_s=latency_s,
        seed=seed,
        raceline=raceline,
        half_width_m=half_width_m,
        driver=dataclasses.replace(sim.Driver(), stops_per_min=stops_per_min),
        camera=sim.Camera() if sensor == "apriltag" else None,
    )
    sim.write_simulation(res, out, force=force)
    return res
