"""Fit recipes (TOML): which drives, which waypoints, what to fit, where the config goes.

out = "levine.json"            # relative to the recipe's folder, and inside it (or absolute)
waypoints = "../../shared/data/levine/levine-waypoints.csv"
holdout = 0.4                  # or [[test_drives]] for separate held-out drives
model = "auto"                 # line or blend by inner validation; or "line" (default), "blend"
solver = "bfgs"                # or "lm"
estimator = "kalman"           # the line model's state estimator (default); or "theil-sen"

[settings]                     # the car and the prediction grid (default: F1TENTH, 10 x 0.1 s)
wheelbase_m = 2.578            # also max_steer_rad, dt_s, horizon

[[drives]]
path = "../../shared/data/levine/actual-poses.csv"
rate_hz = 10                   # also: pose_topic, truth_topic, waypoints, log_time

[[drives]]
path = "drives/camera.bag"     # AprilTag detections + TF: also tag_id (0), drop_outside_tf,
max_tf_gap_s = 0.5             # (the longest TF gap a lookup interpolates across; default per edge)
tag_to_base = [-0.2, 0.0, 0.2, 3.14159]  # and the tag's mount ("x,y,z,yaw" or 4 numbers)

[[drives]]
simulate = { track = "oval", duration_s = 120, latency_s = 0.3, seed = 1 }  # or a track file
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

from fpe_jax import spec as S
from fpe_jax.drive import Drive
from fpe_jax.errors import InputError

DRIVE_KEYS = {"path", "rate_hz", "pose_topic", "truth_topic", "waypoints", "log_time", "simulate"}
DRIVE_KEYS |= {"tag_id", "tag_to_base", "drop_outside_tf", "max_tf_gap_s"}
TOP_KEYS = {"out", "waypoints", "holdout", "fit", "model", "blend", "solver", "drives"}
TOP_KEYS |= {"test_drives", "settings", "estimator"}
SETTINGS_KEYS = S.USER_SETTINGS
SIMULATE_KEYS = {"track", "duration_s", "latency_s", "seed", "raceline", "half_width_m"}
_STR, _BOOL = "a string", "true or false"


def solver_named(name: str, source="solver"):
    """The optimistix solver a solver name of the CLI or a recipe (spec.SOLVERS) stands for.

    "bfgs": BFGS on the scalar robust loss (`fit.default_solver`, the library's default);
    "lm": Levenberg-Marquardt on the residual vector. Both stop on the rms norm of the change,
    not its largest entry (`fit.default_solver` says why). Raises InputError naming `source`
    for another name. Imports JAX: call it only once the solver is needed.
    """
    S.check_choice(name, S.SOLVERS, source, "solver")
    if name == "bfgs":
        from fpe_jax.fit._fit import default_solver

        return default_solver()
    import optimistix as optx

    return optx.LevenbergMarquardt(rtol=1e-3, atol=1e-5, norm=optx.rms_norm)


def _check(ok: object, source, field: str, value, expected: str) -> None:
    if not ok:
        raise InputError(source, f"{field} is {S.short(value)}", expected)


def _check_keys(table: dict, keys, source, what: str) -> None:
    unknown = set(table) - keys
    if unknown:
        raise InputError(source, f"unknown {what} {sorted(unknown)}", f"{sorted(keys)}")


def _check_entry(entry, source, field: str) -> None:
    """The types and ranges of one [[drives]] entry, before anything is loaded."""
    _check(isinstance(entry, dict), source, field, entry, "a table of drive keys")
    _check_keys(entry, DRIVE_KEYS, source, "drive keys")
    for key in ("path", "pose_topic", "truth_topic", "waypoints"):
        if key in entry:
            v = entry[key]
            _check(isinstance(v, str) and v, source, f"{field}.{key}", v, _STR)
    for key in ("log_time", "drop_outside_tf"):
        if key in entry:
            _check(isinstance(entry[key], bool), source, f"{field}.{key}", entry[key], _BOOL)
    if "rate_hz" in entry:
        S.check_rate(entry["rate_hz"], source, f"{field}.rate_hz")
    if "max_tf_gap_s" in entry:
        S.check_tf_gap(entry["max_tf_gap_s"], source, f"{field}.max_tf_gap_s")
    if "tag_id" in entry:
        v = entry["tag_id"]
        _check(S.is_int(v) and v >= 0, source, f"{field}.tag_id", v, "an integer >= 0")
    if "simulate" in entry:
        sim = entry["simulate"]
        expected = 'a table such as { track = "oval", duration_s = 60 }'
        _check(isinstance(sim, dict), source, f"{field}.simulate", sim, expected)
        _check_keys(sim, SIMULATE_KEYS, source, f"{field}.simulate keys")
        for key in ("track", "raceline"):
            if key in sim:
                _check(isinstance(sim[key], str), source, f"{field}.simulate.{key}", sim[key], _STR)
        if "half_width_m" in sim:
            S.number_check(source, f"{field}.simulate.half_width_m", 0.0, 100.0, open_lo=True)(
                sim["half_width_m"]
            )
        S.check_simulation(
            sim.get("duration_s", 60.0),
            sim.get("latency_s", 0.3),
            sim.get("seed", 0),
            0.0,
            source,
            f"{field}.simulate.",
        )


def _confined(base: Path, rel, source, field: str) -> Path:
    """`base / rel`; a relative path must stay inside the recipe's folder."""
    _check(isinstance(rel, str) and rel, source, field, rel, _STR)
    p = Path(rel)
    if p.is_absolute():
        return p
    full = base / p
    if not full.resolve().is_relative_to(base.resolve()):
        raise InputError(
            source,
            f"{field} = {rel!r} leaves the recipe's folder",
            "a path inside it, or an absolute path",
        )
    return full


@dataclasses.dataclass
class Recipe:
    """A loaded recipe: drives with their waypoints (K, 2) [m], and the fit options."""

    source: Path
    out: Path | None
    drives: list[tuple[Drive, object, str]]  # (drive, waypoints xy (K, 2), description)
    test_drives: list[tuple[Drive, object, str]]
    holdout: float
    fit: tuple[str, ...] | None
    blend: str
    model: str | None
    solver: str | None
    estimator: str | None
    settings: dict  # {"[settings] key": (Settings field, value)}, see config.apply_settings
    waypoints: Path | None = None  # the top-level waypoint file (drives may name their own)
    inputs: list[Path] = dataclasses.field(default_factory=list)  # every file it reads


def _load_entry(entry: dict, base: Path, default_wp: str | None, source: Path):
    from fpe_jax import io
    from fpe_jax.io.apriltag import parse_tag_to_base

    if "simulate" in entry:
        from fpe_jax.sim._sim import simulate

        spec = dict(entry["simulate"])
        track = spec.pop("track", "oval")
        files = {k: str(base / v) for k, v in _simulate_files(entry).items()}
        track = files.pop("track", track)
        spec.update(files)  # the raceline file
        res = simulate(track, **spec)
        desc = f"simulate:{track}:seed={spec.get('seed', 0)}:latency={spec.get('latency_s', 0.3)}"
        return res.drive, res.centerline_xy_m, desc
    if "path" not in entry:
        raise InputError(source, "a drive has neither 'path' nor 'simulate'", "one of them")
    wp = entry.get("waypoints", default_wp)
    if wp is None:
        raise InputError(source, f"no waypoints for drive {entry['path']}", "a 'waypoints' key")
    drive = io.load_drive(
        base / entry["path"],
        pose_topic=entry.get("pose_topic"),
        truth_topic=entry.get("truth_topic"),
        rate_hz=entry.get("rate_hz"),
        log_time=entry.get("log_time", False),
        tag_id=entry.get("tag_id"),
        tag_to_base=parse_tag_to_base(entry.get("tag_to_base"), f"{source}: tag_to_base"),
        drop_outside_tf=entry.get("drop_outside_tf", False),
        max_tf_gap_s=entry.get("max_tf_gap_s"),
    )
    return drive, io.load_waypoints(base / wp).xy_m, str(base / entry["path"])


def load_recipe(path) -> Recipe:
    """Read a recipe TOML and load every drive it names (simulated ones are generated)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such recipe file", "a TOML recipe such as fit/levine.toml")
    try:
        spec = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        raise InputError(
            path, f"not UTF-8 text ({e.reason} at byte {e.start})", "a TOML recipe"
        ) from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(path, f"not valid TOML ({e})", "a TOML recipe") from None
    except RecursionError:
        raise InputError(
            path, "nested too deeply", "a TOML recipe such as fit/levine.toml"
        ) from None
    _check_keys(spec, TOP_KEYS, path, "keys")
    if not spec.get("drives"):
        raise InputError(path, "no [[drives]]", "at least one [[drives]] entry")
    # every value is checked before any drive is read or simulated
    table = spec.get("settings", {})
    if not isinstance(table, dict) or set(table) - set(SETTINGS_KEYS):
        bad = sorted(set(table) - set(SETTINGS_KEYS)) if isinstance(table, dict) else table
        raise InputError(path, f"[settings] has {bad!r}", f"keys from {', '.join(SETTINGS_KEYS)}")
    for rule in S.SETTING_RULES:
        if rule.key in table:
            S.check_value(
                rule, table[rule.key], {"settings": table}, path, f"[settings] {rule.key}"
            )
    base = path.parent
    for key in ("drives", "test_drives"):
        entries = spec.get(key, [])
        _check(isinstance(entries, list), path, key, entries, f"[[{key}]] tables")
        for i, e in enumerate(entries):
            _check_entry(e, path, f"{key}[{i}]")
    wp = spec.get("waypoints")
    if wp is not None:
        _check(isinstance(wp, str) and wp, path, "waypoints", wp, _STR)
    holdout = S.check_fraction(spec.get("holdout", 0.3), path, "holdout")
    fit = spec.get("fit")
    if fit is not None:
        _check(isinstance(fit, list), path, "fit", fit, f"a list of names from {S.FIT_NAMES}")
        fit = S.check_fit_names(fit, path, "fit")
    if "model" in spec:
        S.check_choice(spec["model"], S.FIT_MODELS, path, "model")
    S.check_choice(spec.get("blend", "auto"), S.FIT_BLENDS, path, "blend")
    S.check_choice(spec.get("solver", S.DEFAULT_SOLVER), S.SOLVERS, path, "solver")
    if "estimator" in spec:
        S.check_choice(spec["estimator"], S.ESTIMATORS, path, "estimator")
    out = _confined(base, spec["out"], path, "out") if "out" in spec else None
    drives = [_load_entry(e, base, wp, path) for e in spec["drives"]]
    tests = [_load_entry(e, base, wp, path) for e in spec.get("test_drives", [])]
    return Recipe(
        source=path,
        out=out,
        drives=drives,
        test_drives=tests,
        holdout=holdout,
        fit=fit,
        blend=spec.get("blend", "auto"),
        model=spec.get("model"),
        solver=spec.get("solver"),
        estimator=spec.get("estimator"),
        settings={f"[settings] {k}": (k, v) for k, v in table.items()},
        waypoints=None if wp is None else base / wp,
        inputs=[path, *_entry_files(spec, base, wp)],
    )


def _entry_files(spec: dict, base: Path, default_wp: str | None) -> list[Path]:
    """The drive, waypoint and track files the [[drives]] and [[test_drives]] entries read."""
    files = []
    for e in [*spec["drives"], *spec.get("test_drives", [])]:
        for name in (e.get("path"), e.get("waypoints", default_wp) if "path" in e else None):
            if name is not None:
                files.append(base / name)
        files += [base / f for f in _simulate_files(e).values()]
    return files


def _simulate_files(entry: dict) -> dict[str, str]:
    """The files a `simulate` table names: "track" unless a built-in name, "raceline" (relative
    to the recipe's folder, as a drive's path and waypoints are)."""
    from fpe_jax.geometry._tracks import is_builtin

    sim = entry.get("simulate", {})
    named = {k: sim[k] for k in ("track", "raceline") if k in sim}
    if "track" in named and is_builtin(named["track"]):
        del named["track"]
    return named
