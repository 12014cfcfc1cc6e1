"""Observation streams (`fpe run`'s stdin): text lines -> stamped observations, JAX-free.

A line is a CSV row or a JSON object {"t", "x", "y"[, "yaw"]}; blank and `#` lines are skipped,
and so is a byte-order mark before the first line. CSV rows follow the first CSV line:
- a header (names from `fpe_jax.io.tables`) names the columns, t, x, y and optionally yaw;
- without a header a row is `t,x,y,yaw` (four numbers, yaw may be empty). Three header-less
  numbers are the original project's `x,y,z` poses, which carry no stamp: they need `rate_hz`,
  and are never read as t,x,y.
With `rate_hz` (`fpe run --rate HZ`) the k-th observation line (k = 0, 1, ...; a malformed line
counts, a blank, comment or header line does not) is stamped k / HZ, and no line may carry a stamp.

Layout mistakes (the above) raise InputError: they concern every line. A bad line alone (not a
number, a NaN, a position beyond `spec.MAX_COORD_M`, a stamp that is not after the previous one
or jumps more than `spec.MAX_STREAM_GAP_S` ahead, a nanosecond stamp, a last line cut short) is
reported through `warn` with its line number and skipped, and the lines after it are judged
against the last good stamp, so one bad stamp never poisons the rest. When
`spec.RESTART_LINES` consecutive skipped lines agree on a new clock (a restarted recording), the
stream restarts on it.

Numbers are plain ASCII decimal or float syntax (`fpe_jax.io.tables.plain_number`): `1_0` and
other scripts' digits are not numbers. Once a line has ended in a newline, a line without one
is the input cut short (`...,3.` of `...,3.25`): it is reported, never read. Stamps are kept
exact (as decimals) until the stream's time origin, the first stamp's whole seconds when it is
2^20 s or more (epoch stamps), is subtracted: `Observation.since_s` is what the predictor gets,
so epoch and zero-based streams predict the same.
"""

from __future__ import annotations

import dataclasses
import decimal
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator

from fpe_jax import spec
from fpe_jax.errors import InputError
from fpe_jax.io.tables import T_NAMES, X_NAMES, Y_NAMES, YAW_NAMES, plain_number

ORIGIN_FROM_S = 2**20  # stamps from here on (12 days) get a time origin: float64 steps > 0.2 ns
_EXACT = decimal.Context(prec=60)  # enough digits for any stamp a line can carry


@dataclasses.dataclass(frozen=True)
class Observation:
    """One usable line: stamp t [s], position x, y [m] (map frame), yaw [rad] or None.

    `since_s`: the stamp [s] minus the stream's time origin (an integer number of seconds, 0 for
    stamps below ORIGIN_FROM_S), computed exactly before it is rounded to float64.
    `restart`: the observations before this one on the new clock (oldest first), non-empty when the
    stamps restarted here; the consumer forgets its history and feeds these first.
    """

    line: int
    t_s: float
    x_m: float
    y_m: float
    yaw_rad: float | None
    restart: tuple[Observation, ...] = ()
    since_s: float = math.nan
    stamp: decimal.Decimal | None = dataclasses.field(default=None, repr=False, compare=False)


class _Skip(Exception):
    """A line that is reported and skipped (the message says why)."""


def _number(value, what: str) -> float:
    if isinstance(value, decimal.Decimal):  # a JSON number, parsed exactly
        return float(value)
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise _Skip(f"{what} is {spec.short(value)} (expected a number)")
    try:
        return plain_number(value) if isinstance(value, str) else float(value)
    except (ValueError, OverflowError):
        raise _Skip(f"{what} is {spec.short(value)} (expected a number)") from None


def _stamp(value) -> decimal.Decimal:
    """A stamp cell or JSON value [s] as an exact decimal (`_number`'s syntax)."""
    _number(value, "t")  # the same syntax rules and messages
    if isinstance(value, decimal.Decimal):
        return value
    return decimal.Decimal(value.strip() if isinstance(value, str) else value)


class SkipReport:
    """`warn` for `read_observations`: counts the skipped lines and writes their messages to
    `err`, the first `spec.STREAM_MESSAGES` in full, then at most one every
    `spec.STREAM_MESSAGE_EVERY_S` s (saying how many were not shown), so a flood of bad lines
    costs neither memory nor a terminal full of text. `summary()` is the closing count.
    """

    def __init__(self, err, prefix: str = "fpe run: ", clock=time.monotonic):
        self.err, self.prefix, self.clock = err, prefix, clock
        self.n_messages = self.n_skipped = self.n_lines = self._quiet = 0
        self._last_t = -math.inf

    def __call__(self, msg: str) -> None:
        self.n_messages += 1
        self.n_skipped += msg.endswith("; skipped")
        now = self.clock()
        if (
            self.n_messages > spec.STREAM_MESSAGES
            and now - self._last_t < spec.STREAM_MESSAGE_EVERY_S
        ):
            self._quiet += 1
            return
        if self._quiet:
            msg += f" ({self._quiet} more messages not shown since the last)"
        self._quiet, self._last_t = 0, now
        print(self.prefix + msg, file=self.err, flush=True)

    def summary(self) -> str | None:
        """The closing line when messages were held back (else every skip was shown)."""
        if self.n_messages <= spec.STREAM_MESSAGES:
            return None
        return f"{self.prefix}skipped {self.n_skipped} of {self.n_lines} lines"


def header_columns(cells: list[str], rate_hz, source="stdin") -> tuple:
    """Column indices (t, x, y, yaw) of a CSV header (t None with a rate, yaw None if absent),
    and its number of columns."""
    names = [c.strip().lower() for c in cells]
    found = [
        next((names.index(o) for o in options if o in names), None)
        for options in (T_NAMES, X_NAMES, Y_NAMES, YAW_NAMES)
    ]
    header = ",".join(c.strip() for c in cells)
    if rate_hz is not None and found[0] is not None:
        raise InputError(
            source, f"--rate given but the header {header!r} has a time column", "no --rate"
        )
    for what, idx in zip(("t", "x", "y"), found):
        if idx is None and not (what == "t" and rate_hz is not None):
            need = "x,y[,yaw] with --rate" if rate_hz is not None else "t,x,y[,yaw], or --rate HZ"
            raise InputError(source, f"no {what} column in header {header!r}", need)
    return (*found, len(cells))


def parse_line(text: str, columns, rate_hz, source="stdin") -> tuple:
    """(t or None, x, y, yaw or None) of one non-blank line; t [s] is an exact Decimal, None with
    a rate.

    `columns` are a header's indices (see `header_columns`) or None for a header-less row. Raises
    InputError for a layout the whole stream gets wrong, `_Skip` for this line alone.
    """
    if text.startswith("{"):
        try:
            obj = json.loads(text, parse_float=decimal.Decimal)
        except (json.JSONDecodeError, RecursionError) as e:
            msg = e.msg if isinstance(e, json.JSONDecodeError) else "nested too deeply"
            raise _Skip(f"invalid JSON ({msg})") from None
        if rate_hz is not None and isinstance(obj, dict) and "t" in obj:
            raise InputError(source, "--rate given but a JSON line has a stamp t", "no t")
        need = ("x", "y") if rate_hz is not None else ("t", "x", "y")
        if not isinstance(obj, dict) or not set(need) <= obj.keys():
            raise _Skip(f"JSON lacks {', '.join(need[:-1])} or {need[-1]}")
        cells = [obj.get("t"), obj["x"], obj["y"], obj.get("yaw")]
    else:
        raw = [c.strip() for c in text.split(",")]
        if columns is not None:
            if len(raw) != columns[4]:
                raise _Skip(f"{len(raw)} columns (expected {columns[4]}, as the header)")
            cells = [None if c is None else raw[c] for c in columns[:4]]
        elif rate_hz is not None:  # the original's x,y,z poses; z is the height, unused
            if len(raw) != 3:
                raise _Skip(f"{len(raw)} columns (expected x,y,z with --rate)")
            cells = [None, raw[0], raw[1], None]
        elif len(raw) == 3:
            raise InputError(
                source,
                f"a header-less row of 3 numbers ({text[:40]!r}): the original's x,y,z poses "
                "carry no stamps",
                "--rate HZ for x,y,z rows, or a header line t,x,y[,yaw]",
            )
        elif len(raw) == 4:
            cells = raw
        else:
            raise _Skip(f"{len(raw)} columns (expected t,x,y,yaw, or a header line first)")
        if cells[3] == "":
            cells[3] = None
    t = None if rate_hz is not None else _stamp(cells[0])
    x, y = _number(cells[1], "x"), _number(cells[2], "y")
    yaw = None if cells[3] is None else _number(cells[3], "yaw")
    return t, x, y, yaw


def _check_values(t: float, x: float, y: float, yaw: float | None) -> float | None:
    """Skip a line whose numbers cannot be a pose; returns yaw (None for NaN: no orientation)."""
    if not math.isfinite(t):
        raise _Skip(f"stamp is {t} (expected a finite stamp [s])")
    if abs(t) > spec.MAX_STAMP_S:
        raise _Skip(f"stamp {t:.6g} is beyond {spec.MAX_STAMP_S:.6g} s (expected seconds, not ns)")
    for what, v in (("x", x), ("y", y)):
        if not (math.isfinite(v) and abs(v) <= spec.MAX_COORD_M):
            raise _Skip(f"{what} is {v:.6g} (expected a position within ±{spec.MAX_COORD_M:g} m)")
    if yaw is not None and math.isnan(yaw):
        return None
    if yaw is not None and not abs(yaw) <= spec.MAX_YAW_RAD:
        raise _Skip(f"yaw is {yaw:.6g} (expected an angle within ±{spec.MAX_YAW_RAD:g} rad)")
    return yaw


def _origin(t: decimal.Decimal) -> int:
    """The time origin [s] of a clock whose first stamp is t: its whole seconds, or 0 below
    ORIGIN_FROM_S (there float64 seconds are already exact to 0.2 ns)."""
    return int(t.to_integral_value(decimal.ROUND_FLOOR)) if abs(t) >= ORIGIN_FROM_S else 0


def _since(obs: Observation, origin: int) -> Observation:
    if obs.stamp is None:  # stamped by the rate: small already
        return dataclasses.replace(obs, since_s=obs.t_s)
    return dataclasses.replace(obs, since_s=float(_EXACT.subtract(obs.stamp, origin)))


def read_observations(
    lines: Iterable[str],
    warn: Callable[[str], None],
    rate_hz: float | None = None,
    source: str = "stdin",
) -> Iterator[Observation]:
    """The usable observations of `lines`, in order (see the module docstring).

    Args:
        lines: text lines (with or without their newlines), e.g. `iter(sys.stdin.readline, "")`.
        warn: called with "line N: problem; skipped" for every skipped line (and a note where
            the clock restarts); a `SkipReport` also learns the number of observation lines.
        rate_hz: stamps from the rate (k / rate_hz s) instead of from the lines.
    """
    columns, k, last_t = None, 0, None
    seen_csv = newline_seen = False
    origin = None  # the time origin [s] of the current clock
    pending: list[Observation] = []  # skipped lines that agree on a new clock
    for lineno, line in enumerate(lines, 1):
        if lineno == 1:  # a byte-order mark would hide the first header name
            line = line.removeprefix("\ufeff")
        cut_short = newline_seen and not line.endswith("\n")
        newline_seen |= line.endswith("\n")
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        if not seen_csv and not text.startswith("{"):
            seen_csv = True
            if not _is_numeric(text.split(",", 1)[0]):  # a header line names the columns
                columns = header_columns(text.split(","), rate_hz, source)
                continue
        k += 1  # a malformed row still took its sample time
        if isinstance(warn, SkipReport):
            warn.n_lines = k
        try:
            if cut_short:
                raise _Skip("no newline at the end of the input: the line may be cut short")
            t_exact, x, y, yaw = parse_line(text, columns, rate_hz, source)
            t = (k - 1) / rate_hz if rate_hz is not None else float(t_exact)
            yaw = _check_values(t, x, y, yaw)
            obs = Observation(lineno, t, x, y, yaw, stamp=t_exact)
            if last_t is None or last_t < t <= last_t + spec.MAX_STREAM_GAP_S:
                pending.clear()
                last_t = t
                if origin is None:
                    origin = 0 if t_exact is None else _origin(t_exact)
                yield _since(obs, origin)
                continue
            # out of order or far ahead: this line alone is wrong, unless its successors agree
            prev = pending[-1].t_s if pending else None
            if prev is None or not prev < t <= prev + spec.MAX_STREAM_GAP_S:
                pending.clear()
            pending.append(obs)
            if len(pending) == spec.RESTART_LINES:
                warn(
                    f"line {lineno}: the stamps restart at {pending[0].t_s:.6g} s (after "
                    f"{last_t:.6g} s) for {spec.RESTART_LINES} lines: a new history starts"
                )
                last_t = t
                first = pending[0].stamp
                origin = 0 if first is None else _origin(first)
                before = tuple(_since(o, origin) for o in pending[:-1])
                yield dataclasses.replace(_since(obs, origin), restart=before)
                pending.clear()
                continue
            if t <= last_t:
                raise _Skip(f"stamp {t:.6g} s is not after the previous one, {last_t:.6g} s")
            raise _Skip(
                f"stamp {t:.6g} s jumps {t - last_t:.6g} s past the previous one "
                f"(expected at most {spec.MAX_STREAM_GAP_S:g} s)"
            )
        except _Skip as e:
            warn(f"line {lineno}: {e}; skipped")


def _is_numeric(cell: str) -> bool:
    """Whether a first cell reads as a number (so the line is data, not a header)."""
    try:
        plain_number(cell)
    except ValueError:
        # other scripts' digits or `1_0` are still data, to be reported as bad numbers
        return any(c.isdigit() for c in cell) and not any(c.isalpha() for c in cell)
    return True
