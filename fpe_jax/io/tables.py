"""Numeric text tables (CSV and its cousins), shared by the drive and waypoint readers.

One parser for every table format we meet:
- comma, semicolon or whitespace separated (judged from the first data line);
- `#` comment lines anywhere; a header either as the first non-comment line or as the last
  comment line before the data (the F1TENTH centerline/raceline style `# x_m, y_m, ...`);
- no header at all (the 2019 project's files);
- a UTF-8 byte-order mark at the start of the file (ignored).
Numbers are plain ASCII decimal or float syntax (`12`, `-1.5`, `.5e-3`, `nan`, `inf`): Python's
`float` would also take `1_0`, other scripts' digits and non-breaking spaces, which no other tool
reads as numbers, so they are refused. A time column keeps its exact integer nanoseconds
(`Table.t_ns`): `1700000000.123456789` in float64 would already be rounded to ~240 ns.
Malformed input raises InputError naming the file and the line. `read_cars` reads the cars of
`fpe batch` from such a table or from a `.npy` array.
"""

from __future__ import annotations

import dataclasses
import decimal
import os
import re
from pathlib import Path

import numpy as np

from fpe_jax import spec
from fpe_jax.errors import InputError
from fpe_jax.io.ros_msgs import seconds_to_ns

TABLE_SUFFIXES = (".csv", ".txt")

# Accepted spellings of the columns we look for (lower case).
T_NAMES = ("t", "t_s", "time", "stamp", "timestamp")
X_NAMES = ("x", "x_m")
Y_NAMES = ("y", "y_m")
YAW_NAMES = ("yaw", "yaw_rad", "psi", "psi_rad")
SPEED_NAMES = ("v", "v_mps", "speed", "speed_mps", "vx_mps")
STATE_COLUMNS = ("x", "y", "yaw", "v", "yaw_rate")  # the (N, 4|5) layout of `fpe batch`'s cars


# The syntax `plain_number` accepts: ASCII digits, one optional sign, point and exponent; or the
# words nan, inf, infinity (any case, signed).
_PLAIN = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_WORDS = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def plain_number(cell: str) -> float:
    """The float of one cell in plain ASCII number syntax (surrounding blanks allowed).

    Raises ValueError for anything else, `1_0`, non-ASCII digits and `0x10` included.
    """
    s = cell.strip(" \t\r\n")
    if not (_PLAIN.fullmatch(s) or _WORDS.fullmatch(s)):
        raise ValueError(f"not a plain number: {cell!r}")
    return float(s)


def stamp_ns(cell: str) -> int | None:
    """A stamp [s] in plain number syntax -> int [ns], exactly (half to even below 1 ns);
    None for nan/inf. Raises ValueError as `plain_number` does."""
    s = cell.strip(" \t\r\n")
    if _WORDS.fullmatch(s):
        return None
    if not _PLAIN.fullmatch(s):
        raise ValueError(f"not a plain number: {cell!r}")
    return _plain_stamp_ns(s)


def _plain_stamp_ns(s: str) -> int:
    """`stamp_ns` of a cell already known to be a plain finite number (no checks)."""
    whole, _, frac = s.partition(".")
    digits = whole.lstrip("+-")
    if len(frac) <= 9 and digits.isdigit() and "e" not in frac and "E" not in frac:
        ns = int(digits) * 1_000_000_000 + (int(frac.ljust(9, "0")) if frac else 0)
        return -ns if whole.startswith("-") else ns
    return int(decimal.Decimal(s).scaleb(9).to_integral_value(decimal.ROUND_HALF_EVEN))


EXACT_FROM_S = 2.0**20  # below, float64 seconds round to the same nanosecond as the text


def _stamps_ns(t_s: np.ndarray, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(int64 stamps [ns], finite mask) of a time column: from its float64 values where those
    are exact to the nanosecond (|t| < EXACT_FROM_S), else from the text (epoch stamps)."""
    ok = np.isfinite(t_s) & (np.abs(t_s) < 9e9)  # beyond int64 ns a stamp is a unit mistake
    ns = np.zeros(len(t_s), dtype=np.int64)
    if not np.any(np.abs(t_s[ok]) >= EXACT_FROM_S):
        ns[ok] = seconds_to_ns(t_s[ok])
        return ns, ok
    idx = np.flatnonzero(ok)
    ns[idx] = [_plain_stamp_ns(texts[k].strip()) for k in idx]
    return ns, ok


def _is_plain(line: str) -> bool:
    """Whether `float` could only accept plain syntax in this line (the fast common case)."""
    return line.isascii() and "_" not in line


@dataclasses.dataclass(frozen=True)
class Table:
    """A parsed table: data (rows, cols) float64, header lower-cased names or None.

    t_ns: (rows,) int64 stamps [ns] of the time column (the first header name in `T_NAMES`),
    parsed exactly from the text, with t_ok (rows,) False where the cell is nan/inf; None
    without a time column.
    """

    source: Path
    data: np.ndarray
    header: tuple[str, ...] | None
    t_ns: np.ndarray | None = None
    t_ok: np.ndarray | None = None

    def column(self, names: tuple[str, ...], what: str, required: bool = True) -> np.ndarray | None:
        """The (rows,) column whose header is one of `names`; None (or InputError) if absent."""
        found = [n for n in names if n in (self.header or ())]
        if found:
            return self.data[:, self.header.index(found[0])]
        if required:
            raise InputError(
                self.source,
                f"no {what} column in header {','.join(self.header or ())!r}",
                f"a column named {' or '.join(names)}",
            )
        return None


def _is_number(cell: str) -> bool:
    try:
        plain_number(cell)
    except ValueError:
        return False
    return True


def _splitter(line: str):
    for sep in (";", ","):
        if sep in line:
            return lambda s, sep=sep: [c.strip() for c in s.split(sep)]
    return str.split


def read_table(path) -> Table:
    """Parse a numeric text table; see the module docstring for what is accepted.

    Raises InputError for a missing or empty file, ragged rows and non-numeric cells (naming the
    line). NaN/inf cells are kept: the callers decide what a non-finite value means.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "does not exist" if not p.exists() else "is not a file")
    try:
        # utf-8-sig drops a leading byte-order mark ("CSV UTF-8" from spreadsheets), which
        # would otherwise become part of the first header name.
        lines = p.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as e:
        raise InputError(p, f"is not a text file ({e.reason} at byte {e.start})", "a CSV") from e

    comment = None  # the last comment line seen before the first data line
    start = None  # index of the first data (or header) line
    for i, line in enumerate(lines):
        s = line.strip()
        if s.startswith("#"):
            comment = s.lstrip("#").strip()
        elif s:
            start = i
            break
    if start is None:
        raise InputError(p, "has no data rows", "a table of numbers")

    split = _splitter(lines[start])
    first = split(lines[start].strip())
    header = None
    if not all(_is_number(c) for c in first):
        header = tuple(c.lower() for c in first)
        start += 1
    elif comment is not None:
        names = split(comment)
        if len(names) == len(first) and not any(_is_number(c) for c in names):
            header = tuple(c.lower() for c in names)

    rows = []
    ncols = len(header) if header is not None else len(first)
    if header is not None:
        # Names like "x [m]" are common in hand-made files; keep the bare name.
        header = tuple(re.sub(r"\s*[\[(].*$", "", h).strip() for h in header)
        if len(set(header)) != len(header):
            raise InputError(p, f"repeated column names in header {','.join(header)!r}")
    t_col = next((header.index(n) for n in T_NAMES if n in header), None) if header else None
    stamps: list[str] = []  # the time column's text, parsed exactly where float64 is not exact
    for i in range(start, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        cells = split(s)
        if len(cells) != ncols:
            raise InputError(
                p, f"line {i + 1} has {len(cells)} cells", f"{ncols} like the first row"
            )
        try:
            rows.append(
                [float(c) for c in cells] if _is_plain(s) else [plain_number(c) for c in cells]
            )
        except ValueError:
            bad = next(c for c in cells if not _is_number(c))
            raise InputError(p, f"line {i + 1}: non-numeric cell {bad!r}", "numbers") from None
        if t_col is not None:
            stamps.append(cells[t_col])
    if not rows:
        raise InputError(p, "has a header but no data rows", "a table of numbers")
    data = np.asarray(rows, dtype=np.float64)
    t_ns = t_ok = None
    if t_col is not None:
        t_ns, t_ok = _stamps_ns(data[:, t_col], stamps)
    return Table(p, data, header, t_ns, t_ok)


@dataclasses.dataclass(frozen=True)
class _NpyLayout:
    """Where a .npy file's array lies: shape, dtype, C or Fortran order, data offset [bytes]."""

    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    data_start: int


def _check_npy_header(p: Path) -> _NpyLayout:
    """The layout of a .npy; refuse one whose header declares more data than the file holds, or
    than MAX_CARS rows, before anything is allocated (a forged header once asked for 29 TiB)."""
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = {(1, 0): np.lib.format.read_array_header_1_0}.get(
                version, np.lib.format.read_array_header_2_0
            )
            shape, fortran_order, dtype = read(f)
            data_start = f.tell()
    except Exception as e:  # a forged header fails in numpy's parser in many ways (TokenError...)
        raise InputError(p, f"is not a readable .npy array ({e})", "np.save output") from None
    n_bytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    available = p.stat().st_size - data_start
    if n_bytes > available:
        raise InputError(
            p, f"header declares shape {shape} ({n_bytes} bytes) but holds {available}",
            "an intact np.save file",
        )  # fmt: skip
    if shape and shape[0] > spec.MAX_CARS:
        raise InputError(p, f"{shape[0]} cars", f"at most {spec.MAX_CARS} per call; split the file")
    return _NpyLayout(tuple(shape), dtype, bool(fortran_order), data_start)


_CAR_LIMITS = (spec.MAX_COORD_M, spec.MAX_COORD_M, spec.MAX_YAW_RAD, spec.MAX_SPEED_MPS)
_CAR_LIMITS += (spec.MAX_YAW_RATE_RPS,)
CAR_BLOCK = 1 << 16  # cars read and checked at a time when a whole file is scanned


def _car_values_ok(arr: np.ndarray) -> bool:
    """Whether every car (k, 4|5) is finite and within the limits (a quick check of a block)."""
    limits = np.asarray(_CAR_LIMITS[: arr.shape[1]])
    return bool(np.all(np.abs(arr) <= limits))  # NaN compares False


def _check_car_values(p, blocks) -> None:
    """InputError naming `p` for the first problem among the cars, given as consecutive blocks
    (k, 4|5) float64: rows with NaN or inf (their count and the first), else the first column
    (in x, y, yaw, v, yaw_rate order) with a value beyond its limit, and its first car. A float32
    rollout overflows beyond these (1e308 becomes inf): refused, not predicted. The same message
    whatever the blocks."""
    n_bad, first_bad, first_out, start = 0, None, {}, 0
    for arr in blocks:
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        if bad.size and first_bad is None:
            first_bad = start + int(bad[0])
        n_bad += bad.size
        for c in range(arr.shape[1]):
            out = np.flatnonzero(np.abs(arr[:, c]) > _CAR_LIMITS[c])
            if out.size and c not in first_out:
                first_out[c] = (start + int(out[0]), float(arr[out[0], c]))
        start += arr.shape[0]
    if n_bad:
        raise InputError(
            p, f"{n_bad} row(s) with NaN or inf, first car index {first_bad}", "finite numbers"
        )
    for c in sorted(first_out):
        car, value = first_out[c]
        raise InputError(
            p,
            f"{STATE_COLUMNS[c]} of car {car} is {value:g}",
            f"|{STATE_COLUMNS[c]}| <= {_CAR_LIMITS[c]:g}",
        )


def _check_car_count(p, n: int) -> None:
    if n == 0:
        raise InputError(p, "holds no cars", "at least one row")
    if n > spec.MAX_CARS:
        raise InputError(p, f"{n} cars", f"at most {spec.MAX_CARS}; split the file")


@dataclasses.dataclass(frozen=True)
class CarFile:
    """The cars of a file, read a block at a time: what `fpe batch` streams through the predictor.

    A `.npy` (C or Fortran order, any real dtype) is read with one positioned read per block and
    column layout, so memory holds only the blocks in flight, never the file (pages of a memory
    map would count as the process's memory until unmapped); blocks may be read from several
    threads at once. A CSV is read whole by `read_cars` (text is the slow path) and handed out in
    slices. Every block is checked as `read_cars` checks the whole file; a block that fails
    makes the whole file be scanned, so the error is the one `read_cars` gives.

    Attributes:
        path: the file.
        n_cars: N.
        n_columns: 4 or 5 (x [m], y [m], yaw [rad], v [m/s][, yaw rate [rad/s]]).
    """

    path: Path
    n_cars: int
    n_columns: int
    _layout: _NpyLayout | None = None
    _rows: np.ndarray | None = None  # a CSV's cars, read whole

    @classmethod
    def open(cls, path) -> CarFile:
        """Open and check a car file's layout (a .npy's header, or a whole CSV)."""
        p = Path(path)
        if p.suffix.lower() != ".npy":
            arr = read_cars(p)
            return cls(p, arr.shape[0], arr.shape[1], _rows=arr)
        if not p.is_file():
            raise InputError(p, "does not exist", "a .npy array or a CSV of cars")
        lay = _check_npy_header(p)
        real = np.issubdtype(lay.dtype, np.floating) or np.issubdtype(lay.dtype, np.integer)
        if len(lay.shape) != 2 or lay.shape[1] not in (4, 5) or not real or lay.dtype.hasobject:
            raise InputError(
                p,
                f"array of shape {lay.shape} dtype {lay.dtype}",
                "(N, 4|5) x, y, yaw, v[, yaw_rate]",
            )
        _check_car_count(p, lay.shape[0])
        return cls(p, lay.shape[0], lay.shape[1], _layout=lay)

    def read(self, start: int, stop: int) -> np.ndarray:
        """Cars start..stop (k, 4|5) as a new float64 array, checked (InputError naming the
        file, as `read_cars`, if any car of the file is bad)."""
        arr = self._read_raw(start, stop)
        if self._rows is None and not _car_values_ok(arr):
            _check_car_values(self.path, self.blocks(CAR_BLOCK, check=False))
            raise InputError(self.path, "changed while it was read", "a file left alone meanwhile")
        return arr

    def blocks(self, size: int = CAR_BLOCK, *, check: bool = True):
        """Yield the cars in consecutive blocks of `size` rows (the last one shorter)."""
        for start in range(0, self.n_cars, size):
            yield self.read(start, start + size) if check else self._read_raw(start, start + size)

    def _read_raw(self, start: int, stop: int) -> np.ndarray:
        if self._rows is not None:
            return np.array(self._rows[start:stop], dtype=np.float64)
        stop = min(stop, self.n_cars)
        lay, k, cols = self._layout, stop - start, self.n_columns
        item = lay.dtype.itemsize
        raw = np.empty((cols, k) if lay.fortran_order else (k, cols), dtype=lay.dtype)
        with open(self.path, "rb", buffering=0) as f:
            if lay.fortran_order:  # each column lies whole: read its rows start..stop
                for c in range(cols):
                    _pread_into(f, raw[c], lay.data_start + (c * self.n_cars + start) * item)
            else:
                _pread_into(f, raw, lay.data_start + start * cols * item)
        raw = raw.T if lay.fortran_order else raw
        return np.ascontiguousarray(raw, dtype=np.float64)  # native float64 whatever the file's


def _pread_into(f, buf: np.ndarray, offset: int) -> None:
    """Fill the contiguous array `buf` with the file's bytes from `offset` (positioned reads:
    safe from several threads at once)."""
    view = memoryview(buf.reshape(-1).view(np.uint8))
    done = 0
    while done < len(view):
        got = os.preadv(f.fileno(), [view[done:]], offset + done)
        if got == 0:  # the header check saw enough bytes: the file shrank meanwhile
            raise InputError(f.name, "ended before its header's data", "an intact np.save file")
        done += got


def read_cars(path) -> np.ndarray:
    """Cars from a CSV with header `x,y,yaw,v[,yaw_rate]` or a `.npy` (N, 4|5) array.

    Returns (N, 4|5) float64 rows x [m], y [m], yaw [rad], v [m/s][, yaw_rate [rad/s]].
    Raises InputError naming the file and the problem (missing column, NaN row, bad shape).
    `CarFile` reads the same cars a block at a time.
    """
    p = Path(path)
    if p.suffix.lower() == ".npy":
        cars = CarFile.open(p)
        arr = cars._read_raw(0, cars.n_cars)
        _check_car_values(p, [arr])
        return arr
    table = read_table(p)
    if table.header is None:
        raise InputError(p, "has no header", "a header line x,y,yaw,v[,yaw_rate]")
    missing = [c for c in STATE_COLUMNS[:4] if c not in table.header]
    if missing:
        raise InputError(
            p,
            f"header {','.join(table.header)!r} lacks {', '.join(missing)}",
            "columns x,y,yaw,v[,yaw_rate]",
        )
    names = [c for c in STATE_COLUMNS if c in table.header]
    arr = np.column_stack([table.data[:, table.header.index(c)] for c in names])
    _check_car_count(p, arr.shape[0])
    _check_car_values(p, [arr])
    return arr
