"""Export a tuned config to the forms on-car runners take.

- JSON: the normalized config (`fpe_jax.io.config`), the input of the NumPy runner
  (`fpe_jax.runner`).
- ROS 2: a parameter YAML (`<node>:` / `ros__parameters:`) with flat, documented names.
- StableHLO: a `jax.export` artifact of the batched predictor with the parameters and the track
  baked in as constants; it takes the cars' states only (see `INPUTS`). `load(path)` runs it.

Only the StableHLO functions import JAX (inside them), so JSON and ROS 2 exports work without it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import secrets
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from fpe_jax.errors import InputError
from fpe_jax.geometry._path import waypoints_sha256
from fpe_jax.io.config import check_waypoints, read_config, write_config
from fpe_jax.io.writers import check_output_paths, write_bytes
from fpe_jax.spec import FILTER_DEFAULTS

FORMATS = ("json", "ros2", "stablehlo", "all")
DEFAULT_NODE = "future_pose_estimator"
ALL_FILES = {"json": "config.json", "ros2": "params.yaml", "stablehlo": "predictor.stablehlo"}

INPUTS = (
    ("x_m", "position x [m] (the newest observation, or its outlier-free replacement)"),
    ("y_m", "position y [m]"),
    ("yaw_rad", "heading of the car body [rad]"),
    ("v_mps", "speed [m/s]"),
    ("yaw_rate_rps", "yaw rate [rad/s]"),
    ("course_rad", "direction of motion [rad]"),
    ("s_m", "arc length along the track [m] from a windowed projection; NaN: project globally"),
    ("s_fit_m", "frenet / line: track-frame arc length [m]; NaN: from x, y, v, course"),
    ("sdot_mps", "frenet / line: along-track speed [m/s] (track-frame estimate)"),
    ("offset_m", "frenet / line: lateral offset from the path [m], left positive"),
    ("sdot_age_s", "line: age of the speed estimate [s] (the history window's middle)"),
)
WINDOW_INPUTS = (
    ("window_age_s", "kalman: (b, W) age of each window slot before the newest observation [s]"),
    ("window_s_m", "kalman: (b, W) the slots' arc lengths [m] (oldest first)"),
    ("window_d_m", "kalman: (b, W) the slots' lateral offsets [m], left positive"),
    ("window_valid", "kalman: (b, W) 1.0 where a slot holds an observation, else 0.0"),
    ("window_prior", "kalman: (b, 5) Theil-Sen s, ds/dt, d, dd/dt at the newest stamp, age"),
)
"""With the Kalman estimator (frenet / line models) the artifact runs the filter too: after
INPUTS it takes the history window in the track frame (`fpe_jax.model.State`'s window fields,
as `states_from_drive(..., keep_window=True)` gives them); omitted (all slots invalid, prior
NaN) the track-frame estimate of INPUTS is used as given."""

"""The artifact's inputs, in order: each a (b,) float64 array (b >= 1, the batch of cars), the
fields of `fpe_jax.model.State` as `fpe_jax.predict.states_from_drive` estimates them (for the
seed model: the current row's position and observed yaw, as recorded). Output: (b, H, 3) float64
x [m], y [m], yaw [rad] at stamp + h * dt_s, h = 1..H."""

# ROS 2 parameter: (name, config section, config key, type, comment). Types are explicit because
# ROS 2 types parameters by their YAML form: 1 is an integer, 1.0 a double (a node declaring a
# double rejects an integer), so every float is written with a decimal point.
ROS2_PARAMS = (
    ("model", "settings", "model", str, "predictor: blend (linear/pure-pursuit), seed, cv, ctrv"),
    ("blend_mode", "settings", "blend", str, "position: blend positions; heading: turn x (1 - w)"),
    ("lookahead_distance_m", "params", "lookahead_m", float, "pure-pursuit lookahead at 0 m/s [m]"),
    ("lookahead_gain_s", "params", "lookahead_gain_s", float, "lookahead = distance + gain*v [s]"),
    ("blend_weights", "params", "weights", list, "per step, in [0, 1]: 1 linear, 0 pure pursuit"),
    ("delay_offset_s", "params", "delay_s", float, "observation delay, advanced over first [s]"),
    ("speed_weight", "params", "speed_weight", float, "v = w * measured + (1 - w) * typical"),
    ("typical_speed_mps", "params", "speed_mps", float, "speed the measured one shrinks to [m/s]"),
    ("offset_decay_s", "params", "offset_tau_s", float, "frenet/line: lateral offset decay [s]"),
    ("speed_profile_blend_s", "params", "speed_tau_s", float, "line: profile blend-in time [s]"),
    ("pace_return_1ps", "params", "pace_return_1ps", float, "line: pace back to profile [1/s]"),
    ("position_smoothing", "params", "position_smoothing", float, "frenet/line: 0 newest, 1 fit"),
    ("estimator", "settings", "estimator", str, "frenet/line start: kalman or theil-sen"),
    ("filter_accel_mps2", "params", "filter_accel_mps2", float, "kalman: along accel [m/s^2]"),
    ("filter_lat_accel_mps2", "params", "filter_lat_accel_mps2", float, "kalman: lat [m/s^2]"),
    ("filter_obs_m", "params", "filter_obs_m", float, "kalman: observation noise, 1 sigma [m]"),
    ("filter_gate_sigma", "params", "filter_gate_sigma", float, "kalman: innovation gate [sigma]"),
    ("step_s", "settings", "dt_s", float, "time between predicted poses [s]"),
    ("horizon", "settings", "horizon", int, "number of predicted poses H"),
    ("wheelbase_m", "settings", "wheelbase_m", float, "kinematic-bicycle wheelbase [m]"),
    ("max_steering_rad", "settings", "max_steer_rad", float, "steering limit [rad]"),
    ("min_lookahead_m", "settings", "min_lookahead_m", float, "lower bound of the lookahead [m]"),
    ("history", "settings", "history", int, "distinct recent observations the estimate uses"),
)

# the line model's profile, P values each on points spread evenly over the track's arc length
ROS2_LINE_PARAMS = (
    ("line_offset_m", "params", "line_offset_m", list, "line: offset from the centerline [m]"),
    ("line_speed_mps", "params", "line_speed_mps", list, "line: along-track speed [m/s]"),
    ("line_coverage", "params", "line_coverage", list, "line: fit drives' coverage in [0, 1]"),
)


# ---- JSON ----------------------------------------------------------------------------------------


def export_json(cfg: dict[str, Any], out, *, force: bool = False) -> Path:
    """Write the config (as read_config returns it) to `out`; refuses to overwrite unless force."""
    write_config(out, cfg, force=force)
    return Path(out)


# ---- ROS 2 ---------------------------------------------------------------------------------------


def _yaml_scalar(value) -> str:
    """A YAML scalar that YAML 1.1 (PyYAML) and ROS 2 both read back with the same type."""
    if isinstance(value, bool) or value is None:
        raise TypeError(f"unexpected config value {value!r}")
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise InputError("config", f"non-finite value {value!r}", "finite numbers")
        text = repr(value)
        mantissa, e, exponent = text.partition("e")
        # YAML 1.1 reads 1e-06 as a string: it needs a '.' in the mantissa (1.0e-06)
        return mantissa + ("" if "." in mantissa else ".0") + e + exponent
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid double-quoted YAML string
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
    raise TypeError(f"unexpected config value {value!r}")


def to_ros2_yaml(
    cfg: dict[str, Any],
    *,
    node: str = DEFAULT_NODE,
    waypoint_file: str | None = None,
    source: str = "config",
    waypoints_sha256: str | None = None,
) -> str:
    """The config as a ROS 2 parameter file (text): `node:` / `ros__parameters:` / flat names.

    Args:
        cfg: a config dict as `fpe_jax.io.config.read_config` returns it.
        node: the node's name (may carry a namespace, `/ns/node`; `/**` matches every node).
        waypoint_file: path written to `waypoint_file` ("" when None: set it on the car).
        source: the config's file name, for the header comment.
        waypoints_sha256: written when given (`fpe_jax.geometry.waypoints_sha256` of the waypoints).
    """
    if not re.fullmatch(r"/\*\*|/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*", node):
        raise InputError("node", f"{node!r} is not a ROS 2 node name", "letters, digits, _ and /")
    prov = cfg.get("provenance") or {}
    when = prov.get("fitted_at") if isinstance(prov, dict) else None
    fitted = f"; fitted {when}" if when else ""
    header = f"exported by fpe-jax from {source}, config schema_version {cfg['schema_version']}"
    lines = [
        "# Future pose estimator parameters (ROS 2 parameter file)",
        "# " + " ".join((header + fitted).split()),  # one line, whatever the names hold
        f"{node}:",
        "  ros__parameters:",
        "    # version of the fpe-jax config schema these values follow",
        f"    schema_version: {int(cfg['schema_version'])}",
    ]
    # the values of configs from before the frenet / line models and the Kalman estimator
    older = {"offset_tau_s": 1.0, "speed_tau_s": 0.5, "position_smoothing": 0.0}
    older |= {"pace_return_1ps": 0.0} | FILTER_DEFAULTS
    sections = {"params": older | cfg["params"], "settings": cfg["settings"]}
    rows = list(ROS2_PARAMS)
    if cfg["settings"]["model"] == "line":
        rows += ROS2_LINE_PARAMS
    for name, section, key, kind, doc in rows:
        value = sections[section][key]
        value = [float(v) for v in value] if kind is list else kind(value)
        lines += [f"    # {doc}", f"    {name}: {_yaml_scalar(value)}"]
    lines += [
        "    # waypoint / centerline CSV the track is built from (x, y rows, metres, map frame);",
        "    # a relative path is relative to this file's folder",
        f"    waypoint_file: {_yaml_scalar(waypoint_file or '')}",
    ]
    if waypoints_sha256 is not None:
        lines += [
            "    # sha256 of the waypoints (x, y as little-endian float64): `fpe node` checks it",
            f"    waypoints_sha256: {_yaml_scalar(waypoints_sha256)}",
        ]
    return "\n".join(lines) + "\n"


def read_ros2_params(path) -> tuple[dict[str, Any], Path | None]:
    """(config dict, waypoint file or None) from a parameter file `to_ros2_yaml` wrote: the
    first node's `ros__parameters`, a relative waypoint_file taken relative to the file's folder
    and, where the file holds waypoints_sha256, checked against the waypoints. JAX-free (the
    values are the JSON-compatible scalars and lists `_yaml_scalar` writes)."""
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.runner._runner import load_waypoints_xy
    from fpe_jax.spec import check_config

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(path, f"cannot be read ({e.strerror})", "a parameter YAML") from None
    values: dict[str, Any] = {}
    inside = False
    for n, line in enumerate(text.splitlines(), 1):
        body = line.split("#", 1)[0].rstrip() if not line.lstrip().startswith('"') else line
        if not body.strip():
            continue
        if body.strip() == "ros__parameters:":
            inside = True
            continue
        if inside and body.startswith("    "):
            name, _, value = body.strip().partition(":")
            try:
                values[name] = json.loads(value.strip())
            except json.JSONDecodeError:
                raise InputError(
                    path,
                    f"line {n}: {value.strip()!r} is not a value fpe export writes",
                    "numbers, quoted strings and [lists]",
                ) from None
        elif inside:
            break
    if not values:
        raise InputError(
            path, "holds no ros__parameters", "a file `fpe export --format ros2` wrote"
        )
    sections: dict[str, dict] = {"params": {}, "settings": {}}
    for name, section, key, _, _ in ROS2_PARAMS + ROS2_LINE_PARAMS:
        if name in values:
            sections[section][key] = values[name]
    cfg = {"schema_version": values.get("schema_version"), **sections, "uncertainty": None}
    wp = values.get("waypoint_file") or None
    wp_path = None if wp is None else (path.parent / wp)
    if wp_path is not None and cfg["settings"].get("model") == "line":
        cfg["line"] = {"waypoints_sha256": values.get("waypoints_sha256")}
    cfg = check_config(cfg, str(path))
    if wp_path is not None and values.get("waypoints_sha256"):
        if waypoints_sha256(load_waypoints_xy(wp_path)) != values["waypoints_sha256"]:
            raise InputError(
                path,
                f"the waypoints of {wp_path} differ from those it was exported with (sha256)",
                "the exported waypoint file",
            )
    return cfg, wp_path


# ---- StableHLO -----------------------------------------------------------------------------------


def _predictor(params, track):
    """f(x_m, ..., s_m), each (b,) -> (b, H, 3), with params and track closed over (constants):
    the `State` fields named by INPUTS (then WINDOW_INPUTS), in their order."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from fpe_jax.model._state import State
    from fpe_jax.predict._predict import predict_batch

    names = [n for n, _ in INPUTS + WINDOW_INPUTS]

    def f(*inputs):
        states = State(**dict(zip(names, inputs)))
        # only pure pursuit and the Frenet rollouts read the arc length
        if params.settings.model in ("blend", "frenet", "line"):
            # a NaN arc length asks for a global projection; skipped when every car has one
            def global_s(s):
                p = jnp.stack([states.x_m, states.y_m], axis=1)
                return jnp.where(jnp.isfinite(s), s, jax.vmap(track.project)(p))

            s_m = states.s_m
            s = jax.lax.cond(jnp.all(jnp.isfinite(s_m)), lambda s: s, global_s, s_m)
            states = dataclasses.replace(states, s_m=s)
        return predict_batch(params, states, track)

    return f


def export_stablehlo(
    cfg: dict[str, Any],
    waypoints_xy_m,
    out,
    *,
    force: bool = False,
    waypoint_file: str | None = None,
    platforms: tuple[str, ...] = ("cpu", "cuda"),
) -> tuple[Path, Path]:
    """Serialize the batched predictor of `cfg` on the track of `waypoints_xy_m` (K, 2) [m].

    Writes `out` (the `jax.export` serialization) and `out + ".json"` (a sidecar describing the
    inputs, output, platforms, track and config). Computes in float64 (1e-6 m parity with the
    JAX path needs it). `platforms`: lowered for each (default CPU and CUDA, e.g. a Jetson).
    """
    import jax
    from jax import export

    from fpe_jax.geometry._track import Track
    from fpe_jax.io.config import config_to_params
    from fpe_jax.predict._predict import uses_filter

    out = Path(out)
    sidecar = out.with_name(out.name + ".json")
    check_output_paths([out, sidecar], force)
    with jax.enable_x64(True):
        params = config_to_params(cfg)
        track = Track.from_waypoints(np.asarray(waypoints_xy_m, dtype=np.float64))
        (b,) = export.symbolic_shape("b")
        spec = jax.ShapeDtypeStruct((b,), np.float64)
        specs = [spec] * len(INPUTS)
        if uses_filter(params.settings):  # the filter runs inside: the window is an input
            w = params.settings.history
            specs += [jax.ShapeDtypeStruct((b, w), np.float64)] * (len(WINDOW_INPUTS) - 1)
            specs += [jax.ShapeDtypeStruct((b, 5), np.float64)]
        exported = export.export(jax.jit(_predictor(params, track)), platforms=platforms)(*specs)
        blob = exported.serialize()
    h = cfg["settings"]["horizon"]
    meta = {
        "format": "jax.export serialized Exported (jax.export.deserialize)",
        "jax_version": jax.__version__,
        "calling_convention_version": exported.calling_convention_version,
        "platforms": list(exported.platforms),
        "inputs": [{"name": n, "shape": ["b"], "dtype": "float64", "doc": d} for n, d in INPUTS]
        + [
            {"name": n, "shape": ["b", int(a.shape[1])], "dtype": "float64", "doc": d}
            for (n, d), a in zip(WINDOW_INPUTS, exported.in_avals[len(INPUTS) :])
        ],
        "output": {
            "shape": ["b", h, 3],
            "dtype": "float64",
            "doc": f"x [m], y [m], yaw [rad] at stamp + h * dt_s, h = 1..{h}",
        },
        "horizon": h,
        "dt_s": cfg["settings"]["dt_s"],
        "track": {
            "waypoint_file": waypoint_file,
            "waypoints_sha256": hashlib.sha256(
                np.ascontiguousarray(waypoints_xy_m, dtype="<f8").tobytes()
            ).hexdigest(),
            "n_points": int(track.xy_m.shape[0]),
            "closed": track.closed,
            "length_m": float(track.length_m),
        },
        "config": cfg,
    }
    write_bytes(out, blob, force=force)
    write_bytes(sidecar, (json.dumps(meta, indent=2) + "\n").encode(), force=force)
    return out, sidecar


class ExportedPredictor:
    """A loaded StableHLO predictor: `predictor(x_m=..., y_m=..., ...)` -> (b, H, 3) ndarray.

    Arguments by name or in the order of `INPUTS` (then `WINDOW_INPUTS` where the artifact
    runs the Kalman filter: (b, W) and (b, 5) arrays); each a scalar or a (b,) array. Omitted
    optional ones take the `State` defaults: yaw_rate_rps 0, course_rad = yaw_rad, and
    s_m NaN (a global projection on the track), the track-frame estimate NaN (taken from x, y, v
    and the course).

    Attributes:
        exported: the `jax.export.Exported`.
        meta: the sidecar's contents ({} when there is none).
        horizon: H.
    """

    def __init__(self, exported, meta: dict[str, Any]):
        self.exported = exported
        self.meta = meta
        self.horizon = int(exported.out_avals[0].shape[1])

    def __call__(self, *args, **kwargs) -> np.ndarray:
        import jax

        windows = [n for n, _ in WINDOW_INPUTS][: len(self.exported.in_avals) - len(INPUTS)]
        names = [n for n, _ in INPUTS] + windows
        if len(args) > len(names):
            raise TypeError(f"at most {len(names)} inputs: {', '.join(names)}")
        given = dict(zip(names, args))
        for k, v in kwargs.items():
            if k not in names or k in given:
                raise TypeError(f"unexpected or repeated input {k!r}; inputs: {', '.join(names)}")
            given[k] = v
        missing = [n for n in ("x_m", "y_m", "yaw_rad", "v_mps") if n not in given]
        if missing:
            raise TypeError(f"missing inputs: {', '.join(missing)}")
        x = np.atleast_1d(np.asarray(given["x_m"], dtype=np.float64))
        if x.ndim != 1:
            raise ValueError(f"inputs must be scalars or (b,) arrays, got shape {x.shape}")
        defaults = {"yaw_rate_rps": 0.0, "course_rad": given["yaw_rad"]}  # the others: NaN
        arrays = [
            np.broadcast_to(
                np.asarray(given.get(n, defaults.get(n, math.nan)), np.float64), x.shape
            )
            for n in names[: len(INPUTS)]
        ]
        for n, aval in zip(windows, self.exported.in_avals[len(INPUTS) :]):
            shape = (len(x), int(aval.shape[1]))
            default = math.nan if n == "window_prior" else 0.0  # no window: INPUTS as given
            arrays.append(np.broadcast_to(np.asarray(given.get(n, default), np.float64), shape))
        with jax.enable_x64(True):  # the artifact computes in float64
            return np.asarray(self.exported.call(*arrays))


def load(path) -> ExportedPredictor:
    """Load a StableHLO predictor written by `export_stablehlo` (and its sidecar, if present)."""
    from jax import export

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file", "a predictor.stablehlo written by `fpe export`")
    try:
        exported = export.deserialize(bytearray(path.read_bytes()))
    except Exception as e:  # flatbuffers raises assorted errors on foreign bytes
        raise InputError(path, f"not a jax.export artifact ({type(e).__name__}: {e})") from None
    sidecar = path.with_name(path.name + ".json")
    meta = json.loads(sidecar.read_text()) if sidecar.is_file() else {}
    return ExportedPredictor(exported, meta)


# ---- files ---------------------------------------------------------------------------------------


def provenance_waypoints(config_path) -> Path | None:
    """The waypoint file a config was fitted on (its provenance's "waypoints": file and sha256),
    checked to hold the same waypoints still; None when the provenance names none.

    Raises InputError (naming the config or the file) for a malformed entry, a missing file or
    one whose waypoints changed since the fit.
    """
    from fpe_jax.geometry._path import waypoints_sha256
    from fpe_jax.runner._runner import load_waypoints_xy  # JAX-free

    entry = read_config(config_path)["provenance"].get("waypoints")
    if entry is None:
        return None
    if not (
        isinstance(entry, dict)
        and isinstance(entry.get("file"), str)
        and re.fullmatch(r"[0-9a-f]{64}", str(entry.get("sha256")))
    ):
        raise InputError(
            config_path, "provenance.waypoints is malformed", '{"file": PATH, "sha256": HEX}'
        )
    path = Path(entry["file"])
    if not path.is_file():
        raise InputError(
            config_path,
            f"the waypoint file it was fitted on, {path}, is missing",
            "that file, or --waypoints FILE",
        )
    if waypoints_sha256(load_waypoints_xy(path)) != entry["sha256"]:
        raise InputError(
            path,
            f"its waypoints changed since {config_path} was fitted on them (sha256 differs)",
            "the waypoints of the fit, or --waypoints FILE",
        )
    return path


def export_config(
    config_path,
    fmt: str,
    out,
    *,
    node: str = DEFAULT_NODE,
    waypoints=None,
    force: bool = False,
) -> list[Path]:
    """`fpe export`: write `config_path` in format `fmt` to `out` (a folder for "all").

    Args:
        config_path: a tuned config JSON.
        fmt: "json", "ros2", "stablehlo" or "all" (config.json, params.yaml, predictor.stablehlo
            and predictor.stablehlo.json in the folder `out`, created if missing).
        node: ROS 2 node name.
        waypoints: waypoint file; fills `waypoint_file` in the YAML and is baked into the
            StableHLO artifact (required for stablehlo and all).
        force: overwrite existing files, never the config or the waypoints file (whatever the
            spelling: `fpe_jax.io.writers.check_not_input`).

    Returns:
        The paths written. Nothing is written when any target exists without force, or is one
        of the inputs.
    """
    if fmt not in FORMATS:
        raise InputError("fmt", f"unknown format {fmt!r}", f"one of {', '.join(FORMATS)}")
    from fpe_jax.runner._runner import load_waypoints_xy  # JAX-free

    cfg = read_config(config_path)  # every value checked (fpe_jax.spec)
    if fmt in ("stablehlo", "all") and waypoints is None:
        raise InputError(
            "waypoints",
            "the stablehlo predictor bakes the track in, and the config's provenance names no "
            "waypoint file",
            "--waypoints FILE",
        )
    # everything that can fail on input is checked before anything is written
    xy = None
    if waypoints is not None:  # a line config runs only on the waypoints it was learned on
        xy = load_waypoints_xy(waypoints)
        check_waypoints(cfg, config_path, xy, waypoints)
    text = None
    out = Path(out)
    if fmt in ("ros2", "all"):
        # relative to the YAML's folder, so the exported folder can be copied to the car whole
        yaml_dir = (out if fmt == "all" else out.parent).resolve()
        wp_name = (
            None if waypoints is None else os.path.relpath(Path(waypoints).resolve(), yaml_dir)
        )
        sha = None if xy is None else waypoints_sha256(xy)
        text = to_ros2_yaml(
            cfg,
            node=node,
            waypoint_file=wp_name,
            source=Path(config_path).name,
            waypoints_sha256=sha,
        )
    inputs = (config_path, waypoints)  # never replaced, --force or not
    if fmt != "all":
        sidecar = [out.with_name(out.name + ".json")] if fmt == "stablehlo" else []
        check_output_paths([out, *sidecar], force, inputs)
        return _write_formats(cfg, xy, text, {fmt: out}, waypoints, force)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is not a folder", "a folder for config.json, params.yaml, ...")
    hlo = ALL_FILES["stablehlo"]
    names = [hlo, hlo + ".json", ALL_FILES["json"], ALL_FILES["ros2"]]  # the order written
    if out.exists():
        check_output_paths([out / n for n in names], force, inputs)
    else:
        check_output_paths([out], force)  # its parent exists and is writable
    # the set is written whole in a hidden folder beside `out` and moved in only when complete:
    # a failure (a full disk) leaves no partial or mixed set that a car could deploy
    stage = out.with_name(f".{out.name[:64]}.{os.getpid()}.{secrets.token_hex(4)}.part")
    stage.mkdir()
    try:
        targets = {k: stage / name for k, name in ALL_FILES.items()}
        _write_formats(cfg, xy, text, targets, waypoints, force=False)
        if not out.exists():
            stage.rename(out)
        else:  # other files of the user's folder stay; each of ours is replaced by a rename
            for n in names:
                os.replace(stage / n, out / n)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return [out / n for n in names]


def _write_formats(cfg, xy, text, targets: dict, waypoints, force: bool) -> list[Path]:
    """Write each format of `targets` (format -> path) for `export_config`: the paths written."""
    written = []
    if "stablehlo" in targets:  # first: the slowest, and the only one that can fail late
        written += export_stablehlo(
            cfg, xy, targets["stablehlo"], force=force, waypoint_file=str(waypoints)
        )
    if "json" in targets:
        written.append(export_json(cfg, targets["json"], force=force))
    if "ros2" in targets:
        write_bytes(targets["ros2"], text.encode(), force=force)
        written.append(targets["ros2"])
    return written
