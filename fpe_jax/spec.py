"""The JAX-free spec: model, blend, fit-group and solver names, the config schema and every check
of a config's values.

Imported by params (Settings), config, recipe, export, the CLI and the NumPy runner, so one table
of rules decides what a valid value is everywhere. Each failure is an `InputError` naming the file
and the field (`settings.dt_s`), what it is and what was expected.

To add a config field, add one `Rule` to PARAM_RULES or SETTING_RULES; `check_config` and
`check_settings` pick it up.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from fpe_jax.errors import InputError

SCHEMA_VERSION = 2
BLEND_MODES = ("position", "heading")
MODELS = ("blend", "seed", "cv", "ctrv", "frenet", "line")
MIN_TAU_S = 0.01  # time constants stay above this: exp(-t / tau) must not underflow to 0/0
# the track-frame state estimators of the frenet and line models: a Kalman filter over the
# history window (`fpe_jax.model`) or Theil-Sen lines (`fpe_jax.model.track_frame_lines`)
ESTIMATORS = ("kalman", "theil-sen")
DEFAULT_ESTIMATOR = "theil-sen"  # what a config without settings.estimator was fitted with
# The line model's estimator in a new fit unless told otherwise: the Kalman filter in the track
# frame (with its fitted values under the fit's prior, `fpe_jax.fit.FILTER_PRIOR_M2`). On the
# held-out drives of Levine, oval, hairpin and Austin it scored FDE 0.447, 0.437, 0.378 and
# 0.476 m against the Theil-Sen lines' 0.445, 0.465, 0.404 and 0.491 m.
LINE_ESTIMATOR = "kalman"
# the filter's noise values stay above these (positive by reparametrisation); a gate below one
# sigma would reject most good observations
MIN_FILTER_NOISE = 1e-3
MIN_GATE_SIGMA = 1.0
# The Kalman estimator's values before fitting (and the centre of the fit's prior on them), and
# for configs written without them. Unfitted, the line model predicted the held-out drives of
# Levine, oval, hairpin and Austin as well as or better than with Theil-Sen with these (FDE
# 0.447, 0.437, 0.378, 0.481 m against 0.445, 0.465, 0.404, 0.491 m); a more responsive filter
# (3.0 m/s^2, 0.15 m) was worse on all four (0.478, 0.503, 0.468, 0.545 m).
FILTER_DEFAULTS = {
    "filter_accel_mps2": 1.0,
    "filter_lat_accel_mps2": 1.0,
    "filter_obs_m": 0.3,
    "filter_gate_sigma": 4.0,
}

# Declared limits on sizes, checked before the work starts (each beyond is one line, exit 2).
# The estimator keeps 1 s of observations (100 at 100 Hz) and compares every pair: 1000 took
# 263 s and 8.7 GB for 220 observations.
MAX_HISTORY = 100
MAX_WAYPOINTS = 1_000_000  # more is a point cloud, not a reference line
MIN_TRACK_LENGTH_M, MAX_TRACK_LENGTH_M = 1.0, 100_000.0  # km or mm mistaken for m beyond
MAX_CARS = 1 << 28  # cars per batch file (2.7e8 rows of 5 float64 are 10.7 GB)
MAX_CARS_PER_CALL = 1 << 20  # one compiled call holds ~1.2 KB per car: 1.3 GB here
MAX_SPEED_MPS = 200.0  # any car's speed, fitted or given
MAX_YAW_RATE_RPS = 100.0
MAX_COORD_M = 1e8  # UTM northings stay below 1e7 m; 1e308 would overflow the estimate
MAX_YAW_RAD = 1e6  # unwrapped yaw of many laps is fine; 1e308 is not an angle
# Observation streams (`fpe run`, fpe_jax.io.stream): a line beyond these is reported and skipped.
MAX_STAMP_S = 2.0**32  # ROS 1's unsigned seconds end in 2106: beyond is ms, us or ns
MAX_STREAM_GAP_S = 60.0  # a stamp further past the previous one is a glitch ...
RESTART_LINES = 3  # ... unless this many consecutive lines agree on the new clock

# `--fit` names -> the Params fields they free (fpe_jax.fit fits these groups)
FIT_GROUPS = {
    "lookahead": ("lookahead_m", "lookahead_gain_s"),
    "lookahead_m": ("lookahead_m",),
    "gain": ("lookahead_gain_s",),
    "weights": ("weights",),
    "delay": ("delay_s",),
    "speed": ("speed_weight", "speed_mps"),
    "tau": ("offset_tau_s", "speed_tau_s"),
    "pace": ("pace_return_1ps",),
    "smoothing": ("position_smoothing",),
    "filter": ("filter_accel_mps2", "filter_lat_accel_mps2", "filter_obs_m", "filter_gate_sigma"),
}
FIT_NAMES = tuple(FIT_GROUPS)
# the blend model's default groups: not "speed", whose shrinkage toward a typical speed learns the
# fit drive's pace (fitted on a slow oval drive it missed the fast laps: FDE 1.61 m); the blend
# then drives at the measured speed (speed_weight 1)
DEFAULT_FIT = ("lookahead", "weights", "delay")
SOLVERS = ("bfgs", "lm")  # optimistix BFGS on the robust loss (default), LM on the residuals
DEFAULT_SOLVER = SOLVERS[0]
FIT_BLENDS = ("auto", *BLEND_MODES)
# the models `fpe fit --model` fits (fpe_jax.fit.MODEL_FIT); "auto": line or blend, whichever
# predicts the training data's inner validation split better
FIT_MODELS = ("auto", "line", "blend")
# Settings a user may change on a predictor (flags --wheelbase, --max-steer, --dt, --horizon and
# a recipe's [settings] table): the car and the prediction grid, never the model's form.
USER_SETTINGS = ("wheelbase_m", "max_steer_rad", "dt_s", "horizon")
# the longest prediction a config, a flag or a recipe may ask for [steps]: planners read 3-5 s
# ahead (50 steps of 0.1 s); beyond this a rollout no longer predicts a car's near future
MAX_HORIZON = 1000


def is_number(v) -> bool:
    """A finite real number (int or float, NumPy scalars included; not bool, not a string)."""
    if isinstance(v, bool) or not hasattr(v, "__float__") or isinstance(v, str | bytes):
        return False
    try:
        return math.isfinite(float(v))
    except (TypeError, ValueError, OverflowError):
        return False


def is_int(v) -> bool:
    """An integer (Python or NumPy), not bool."""
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


@dataclasses.dataclass(frozen=True)
class Rule:
    """What one config field may hold.

    kind: "number" (finite real), "int", "choice" (one of `choices`), "weights" (a list of
    settings.horizon numbers), "array" (a non-empty list of numbers). lo / hi: inclusive bounds
    unless lo_open / hi_open; a bound given as a string names another field of the same config
    (`"settings.min_lookahead_m"`). optional: the key may be absent (configs written before it).
    """

    key: str
    kind: str = "number"
    lo: float | int | str | None = None
    hi: float | int | str | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()
    unit: str = ""
    optional: bool = False

    def expected(self) -> str:
        if self.kind == "choice":
            return f"one of {', '.join(self.choices)}"
        what = {
            "number": "a finite number",
            "int": "an integer",
            "weights": "a list of settings.horizon finite numbers",
            "array": "a non-empty list of finite numbers",
        }[self.kind]
        lo = "" if self.lo is None else f"{'>' if self.lo_open else '>='} {self.lo}"
        hi = "" if self.hi is None else f"{'<' if self.hi_open else '<='} {self.hi}"
        rng = " and ".join(r for r in (lo, hi) if r)
        each = " each" if self.kind in ("weights", "array") else ""
        return f"{what}{each} {rng}{' ' + self.unit if self.unit and rng else ''}".strip()


PARAM_RULES = (
    Rule("lookahead_m", lo="settings.min_lookahead_m", hi=1000.0, unit="m"),
    Rule("lookahead_gain_s", lo=0.0, hi=100.0, unit="s"),
    Rule("weights", "weights", lo=0.0, hi=1.0),
    Rule("delay_s", lo=0.0, hi=10.0, unit="s"),
    Rule("speed_weight", lo=0.0, hi=1.0),
    Rule("speed_mps", lo=0.0, hi=MAX_SPEED_MPS, unit="m/s"),
    Rule("offset_tau_s", lo=MIN_TAU_S, hi=1000.0, unit="s", optional=True),
    Rule("speed_tau_s", lo=MIN_TAU_S, hi=1000.0, unit="s", optional=True),
    Rule("pace_return_1ps", lo=0.0, hi=1000.0, unit="1/s", optional=True),
    Rule("position_smoothing", lo=0.0, hi=1.0, optional=True),
    Rule("filter_accel_mps2", lo=MIN_FILTER_NOISE, hi=1000.0, unit="m/s^2", optional=True),
    Rule("filter_lat_accel_mps2", lo=MIN_FILTER_NOISE, hi=1000.0, unit="m/s^2", optional=True),
    Rule("filter_obs_m", lo=MIN_FILTER_NOISE, hi=100.0, unit="m", optional=True),
    Rule("filter_gate_sigma", lo=MIN_GATE_SIGMA, hi=1000.0, optional=True),
)
# the line model's profile along the track (`fpe_jax.model`), P values each; required for it
LINE_RULES = (
    Rule("line_offset_m", "array", lo=-1000.0, hi=1000.0, unit="m"),
    Rule("line_speed_mps", "array", lo=0.0, hi=MAX_SPEED_MPS, unit="m/s"),
    Rule("line_coverage", "array", lo=0.0, hi=1.0),
)
SETTING_RULES = (
    Rule("dt_s", lo=0.0, hi=10.0, lo_open=True, unit="s"),
    Rule("horizon", "int", lo=1, hi=MAX_HORIZON),
    Rule("wheelbase_m", lo=0.0, hi=100.0, lo_open=True, unit="m"),
    # >= pi/2 makes tan(steer) flip sign
    Rule("max_steer_rad", lo=0.0, hi=0.5 * math.pi, lo_open=True, hi_open=True, unit="rad"),
    Rule("blend", "choice", choices=BLEND_MODES),
    Rule("model", "choice", choices=MODELS),
    Rule("min_lookahead_m", lo=0.0, hi=1000.0, unit="m"),
    Rule("history", "int", lo=2, hi=MAX_HISTORY),
    Rule("estimator", "choice", choices=ESTIMATORS, optional=True),
)
PARAM_KEYS = tuple(r.key for r in PARAM_RULES if not r.optional)
FILTER_KEYS = FIT_GROUPS["filter"]
OPTIONAL_PARAM_KEYS = tuple(r.key for r in PARAM_RULES if r.optional)
LINE_KEYS = tuple(r.key for r in LINE_RULES)
SETTING_KEYS = tuple(r.key for r in SETTING_RULES)
SETTING_DEFAULTS = {"estimator": DEFAULT_ESTIMATOR}  # the optional settings' values when absent
SECTIONS = {"params": PARAM_RULES, "settings": SETTING_RULES}


def _bound(b, cfg: dict) -> float | None:
    if isinstance(b, str):
        section, key = b.split(".")
        v = cfg.get(section, {}).get(key)
        return float(v) if is_number(v) else None
    return None if b is None else float(b)


def _in_range(x: float, rule: Rule, cfg: dict) -> bool:
    lo, hi = _bound(rule.lo, cfg), _bound(rule.hi, cfg)
    if lo is not None and (x <= lo if rule.lo_open else x < lo):
        return False
    return not (hi is not None and (x >= hi if rule.hi_open else x > hi))


def short(v, n: int = 40) -> str:
    """A value as an error message shows it: repr cut to n characters, containers by size."""
    s = repr(v) if not isinstance(v, list | dict) else type(v).__name__ + f" of {len(v)}"
    return s if len(s) <= n else s[: n - 3] + "..."


def check_value(rule: Rule, v, cfg: dict, source, field: str) -> None:
    """Raise InputError(source, "field is v", expected) unless `v` satisfies `rule`."""
    bad = InputError(source, f"{field} is {short(v)}", rule.expected())
    if rule.kind == "choice":
        if not (isinstance(v, str) and v in rule.choices):
            raise bad
        return
    if rule.kind == "array":
        ok = isinstance(v, list) and v and all(is_number(x) for x in v)
        if not ok or not all(_in_range(float(x), rule, cfg) for x in v):
            raise bad
        return
    if rule.kind == "weights":
        horizon = cfg.get("settings", {}).get("horizon")
        if not isinstance(v, list) or not all(is_number(w) for w in v):
            raise bad
        if is_int(horizon) and len(v) != horizon:
            raise InputError(
                source,
                f"{field} is a list of {len(v)} for settings.horizon {horizon}",
                f"{horizon} weights",
            )
        if not all(_in_range(float(w), rule, cfg) for w in v):
            raise bad
        return
    if not is_number(v) or (rule.kind == "int" and not is_int(v)):
        raise bad
    if not _in_range(float(v), rule, cfg):
        raise bad


def check_settings(values: dict, source="Settings") -> None:
    """Check settings values alone (Settings.__post_init__)."""
    cfg = {"settings": values}
    for rule in SETTING_RULES:
        check_value(rule, values[rule.key], cfg, source, f"settings.{rule.key}")


def _check_uncertainty(unc, horizon: int, source) -> None:
    """null, or {"frame": "track", "cov_m2": (H, 2, 2) symmetric positive semi-definite [m^2]},
    with optional per-prediction terms state_scale (H, 2) >= 0, model_var_m2 (H, 2) >= 0 [m^2]
    and correlation (H,) in [-1, 1]."""
    if unc is None:
        return
    want = f'null or {{"frame": "track", "cov_m2": {horizon} x 2 x 2 numbers}}'
    if not isinstance(unc, dict) or unc.get("frame") != "track" or "cov_m2" not in unc:
        raise InputError(source, f"uncertainty is {short(unc)}", want)
    cov = unc["cov_m2"]
    if not isinstance(cov, list) or len(cov) != horizon:
        n = len(cov) if isinstance(cov, list) else short(cov)
        raise InputError(source, f"uncertainty.cov_m2 has {n} steps", f"{horizon} (the horizon)")
    for h, c in enumerate(cov):
        ok = (
            isinstance(c, list)
            and len(c) == 2
            and all(isinstance(r, list) and len(r) == 2 and all(map(is_number, r)) for r in c)
        )
        if ok:
            (a, b), (b2, d) = c
            ok = a >= 0 and d >= 0 and abs(b - b2) <= 1e-9 * max(1.0, abs(a), abs(d))
            ok = ok and a * d - b * b >= -1e-9 * max(1.0, a * d)
        if not ok:
            raise InputError(
                source,
                f"uncertainty.cov_m2[{h}] is {short(c)}",
                "a symmetric positive semi-definite 2 x 2 matrix of finite numbers [m^2]",
            )
    # the per-prediction terms (`fpe_jax.evaluate.fit_uncertainty`): all three or none
    terms = {"state_scale": (2, 0.0, None), "model_var_m2": (2, 0.0, None)}
    terms["correlation"] = (None, -1.0, 1.0)
    given = [k for k in terms if k in unc]
    if given and len(given) != len(terms):
        raise InputError(source, f"uncertainty has {', '.join(given)} only", ", ".join(terms))
    for key, (width, lo, hi) in terms.items() if given else ():
        rows = unc[key]
        for h in range(horizon):
            row = rows[h] if isinstance(rows, list) and len(rows) == horizon else None
            vals = row if width else [row]
            ok = isinstance(vals, list) and len(vals) == (width or 1)
            ok = ok and all(is_number(v) and v >= lo and (hi is None or v <= hi) for v in vals)
            if not ok:
                shape = f"{horizon} x {width}" if width else f"{horizon}"
                bound = f">= {lo:g}" if hi is None else f"in [{lo:g}, {hi:g}]"
                raise InputError(
                    source, f"uncertainty.{key} is {short(rows)}", f"{shape} numbers {bound}"
                )


def check_config(cfg: Any, source) -> dict:
    """Check a parsed config: schema version, sections, keys, every value and the cross-field
    rules (weights and uncertainty match the horizon). Returns it with `uncertainty` and
    `provenance` defaulted. Raises InputError naming the file and the field."""
    if not isinstance(cfg, dict) or "schema_version" not in cfg:
        raise InputError(source, "missing 'schema_version'", f"schema_version {SCHEMA_VERSION}")
    version = cfg["schema_version"]
    if not is_int(version) or version > SCHEMA_VERSION or version < 1:
        raise InputError(
            source,
            f"schema_version {short(version)} is not supported (newer than this fpe-jax?)",
            f"schema_version <= {SCHEMA_VERSION}; upgrade fpe-jax to read it",
        )
    line_model = isinstance(cfg.get("settings"), dict) and cfg["settings"].get("model") == "line"
    rules = dict(SECTIONS, params=PARAM_RULES + (LINE_RULES if line_model else ()))
    for section, section_rules in rules.items():
        keys = [r.key for r in section_rules]
        if not isinstance(cfg.get(section), dict):
            raise InputError(source, f"missing section '{section}'", f"keys {', '.join(keys)}")
        missing = [r.key for r in section_rules if not r.optional and r.key not in cfg[section]]
        if missing:
            what = f"'{section}' lacks {', '.join(missing)}"
            if line_model and set(missing) <= set(LINE_KEYS):
                what = f"model 'line' without {', '.join(f'params.{k}' for k in missing)}"
            raise InputError(source, what, "every key present (a config written by `fpe fit`)")
        unknown = sorted(set(cfg[section]) - set(keys))
        if unknown:
            raise InputError(
                source, f"unknown key {section}.{unknown[0]}", f"keys {', '.join(keys)}"
            )
    # settings first: the params' rules refer to them (horizon, min_lookahead_m)
    for section in ("settings", "params"):
        for rule in rules[section]:
            if rule.key in cfg[section]:
                v = cfg[section][rule.key]
                check_value(rule, v, cfg, source, f"{section}.{rule.key}")
    if line_model:
        sizes = {len(cfg["params"][k]) for k in LINE_KEYS}
        if len(sizes) != 1:
            raise InputError(source, "line profile arrays differ in size", "P values each")
        line = cfg.get("line")
        if not (isinstance(line, dict) and isinstance(line.get("waypoints_sha256"), str)):
            what = "model 'line' without line.waypoints_sha256"
            raise InputError(source, what, "a config written by `fpe fit`")
    for key, value in SETTING_DEFAULTS.items():  # configs written before the key
        cfg["settings"].setdefault(key, value)
    if version < 2 and cfg["settings"]["estimator"] == "kalman":
        # schema 1 started the Kalman estimator's rollouts from the filter's position alone;
        # position_smoothing (then the Theil-Sen estimator's only) now applies to both
        cfg["params"]["position_smoothing"] = 1.0
    cfg.setdefault("uncertainty", None)
    _check_uncertainty(cfg["uncertainty"], cfg["settings"]["horizon"], source)
    cfg.setdefault("provenance", {})
    if not isinstance(cfg["provenance"], dict):
        raise InputError(source, f"provenance is {short(cfg['provenance'])}", "an object")
    return cfg


def check_choice(value, choices, source, field: str) -> None:
    """Raise InputError unless `value` is one of `choices` (strings)."""
    if not (isinstance(value, str) and value in choices):
        raise InputError(source, f"{field} is {short(value)}", f"one of {', '.join(choices)}")


def check_fraction(value, source, field: str) -> float:
    """A held-out fraction strictly between 0 and 1."""
    if not is_number(value) or not 0.0 < float(value) < 1.0:
        raise InputError(source, f"{field} is {short(value)}", "a fraction in (0, 1) such as 0.3")
    return float(value)


def check_fit_names(names, source, field: str) -> tuple[str, ...]:
    """A non-empty list of --fit group names."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",")]
    if (
        not isinstance(names, list | tuple)
        or not names
        or not all(isinstance(n, str) and n for n in names)
    ):
        raise InputError(source, f"{field} is {short(names)}", f"names from {FIT_NAMES}")
    bad = [n for n in names if n not in FIT_GROUPS]
    if bad:
        raise InputError(source, f"{field}: unknown {', '.join(bad)}", f"names from {FIT_NAMES}")
    return tuple(names)


def number_check(
    source, field: str, lo: float | None = None, hi: float | None = None, *, open_lo=False
) -> Callable[[Any], float]:
    """A checker for one flag: finite number within [lo, hi] (lo exclusive if open_lo)."""

    rule = Rule(field, lo=lo, hi=hi, lo_open=open_lo)

    def check(v) -> float:
        check_value(rule, v, {}, source, field)
        return float(v)

    return check


MAX_DURATION_S = 7200.0  # two hours: the closed-loop simulator keeps its rows in Python lists


MIN_RATE_HZ, MAX_RATE_HZ = 1e-3, 1e6  # a rate outside this is a unit mistake


def check_rate(v, source, field: str) -> float:
    """A sample rate [Hz]: a finite positive number, and not absurd (1e-300 would stamp every row
    t = 0)."""
    hz = number_check(source, field, 0.0, open_lo=True)(v)
    if not MIN_RATE_HZ <= hz <= MAX_RATE_HZ:
        raise InputError(
            source, f"{field} {hz:g} is absurd", f"{MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz"
        )
    return hz


def check_chunk(chunk) -> int:
    """Cars per compiled call (`fpe batch --chunk`): an integer in [1, MAX_CARS_PER_CALL]."""
    if not (is_int(chunk) and 1 <= chunk <= MAX_CARS_PER_CALL):
        raise InputError(
            "chunk", f"{short(chunk)} cars per call", f"an integer from 1 to {MAX_CARS_PER_CALL}"
        )
    return int(chunk)


def check_track_size(n_waypoints: int, length_m: float, source) -> None:
    """Waypoints within the declared limits: at most MAX_WAYPOINTS, and a polyline between
    MIN_TRACK_LENGTH_M and MAX_TRACK_LENGTH_M long (the resampled path has one point per 0.1 m)."""
    if n_waypoints > MAX_WAYPOINTS:
        raise InputError(source, f"{n_waypoints} waypoints", f"at most {MAX_WAYPOINTS}")
    if not MIN_TRACK_LENGTH_M <= length_m <= MAX_TRACK_LENGTH_M:
        raise InputError(
            source,
            f"the waypoints span a path {length_m:.6g} m long (in other units than metres?)",
            f"a track {MIN_TRACK_LENGTH_M:g} m to {MAX_TRACK_LENGTH_M:g} m long, in metres",
        )


def check_simulation(
    duration_s, latency_s, seed, stops_per_min, source="simulate", prefix=""
) -> None:
    """The simulator's numbers: duration in (0, a day] s, latency in [0, duration) s, an integer
    seed >= 0, stops per minute in [0, 60]."""
    duration_s = number_check(source, f"{prefix}duration_s", 0.0, MAX_DURATION_S, open_lo=True)(
        duration_s
    )
    latency_s = number_check(source, f"{prefix}latency_s", 0.0)(latency_s)
    if latency_s >= duration_s:
        raise InputError(
            source,
            f"{prefix}latency_s {latency_s:g} s is not below the duration {duration_s:g} s",
            "a latency shorter than the drive (no detection would be recorded)",
        )
    if not (is_int(seed) and seed >= 0):
        raise InputError(source, f"{prefix}seed is {short(seed)}", "an integer >= 0")
    number_check(source, f"{prefix}stops_per_min", 0.0, 60.0)(stops_per_min)


# --- readers: TF, AprilTag mounts, simulated tracks, stream messages --------------------------

MAX_TF_GAP_S = 3600.0  # --max-tf-gap: interpolating a TF edge across more is never meant
MAX_TAG_OFFSET_M = 10.0  # a tag on a car sits within this of the car's base frame
MAX_TAG_YAW_RAD = 2 * math.pi
MAX_HALF_WIDTH_M = 50.0  # a track's half-width: F1TENTH ~1.1 m, a race circuit ~8 m
STREAM_MESSAGES = 10  # `fpe run` prints this many skipped-line messages, then one per ...
STREAM_MESSAGE_EVERY_S = 10.0  # ... this many seconds, each with the count since the last


def check_tf_gap(v, source, field: str = "--max-tf-gap") -> float:
    """The longest TF gap [s] a lookup may interpolate across: a number in (0, MAX_TF_GAP_S]."""
    return number_check(source, field, 0.0, MAX_TF_GAP_S, open_lo=True)(v)


def check_tag_mount(values, source="--tag-to-base") -> tuple[float, float, float, float]:
    """X, Y, Z [m] of a tag's centre in the car's base frame, each within ±MAX_TAG_OFFSET_M, and
    the way it faces, YAW [rad], within ±MAX_TAG_YAW_RAD: four finite numbers."""
    expected = (
        f"X,Y,Z,YAW: the tag's centre in the car's base frame, each within "
        f"±{MAX_TAG_OFFSET_M:g} m, and the way it faces, within ±{MAX_TAG_YAW_RAD:.4g} rad"
    )
    try:  # a string here is one the caller could not split into four numbers
        out = () if isinstance(values, str) else tuple(float(v) for v in values)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 4 or not all(math.isfinite(v) for v in out):
        shown = short(values if isinstance(values, str) else ",".join(map(str, values)))
        raise InputError(source, f"{shown} is not four finite numbers", expected)
    if max(abs(v) for v in out[:3]) > MAX_TAG_OFFSET_M or abs(out[3]) > MAX_TAG_YAW_RAD:
        shown = ",".join(f"{v:g}" for v in out)
        raise InputError(source, f"{shown} is out of range", expected)
    return out  # type: ignore[return-value]


def check_half_width(v, source="--half-width") -> float:
    """A track's half-width [m]: a finite number in (0, MAX_HALF_WIDTH_M]."""
    if not (is_number(v) and 0.0 < float(v) <= MAX_HALF_WIDTH_M):
        raise InputError(source, f"{short(v)} m", f"a half-width in (0, {MAX_HALF_WIDTH_M:g}] m")
    return float(v)
