"""Numeric text tables (CSV and its cousins), shared by the drive and waypoint readers.

One parser for every table format we meet:
- comma, semicolon or whitespace separated (judged from the first data line);
- `#` comment lines anywhere; a header either as the first non-comment line or as the last
  comment line before the data (the F1TENTH centerline/raceline style `# x_m, y_m, ...`);
- no header at all (the 2019 project's files);
- a UTF-8 byte-order mark at the start of the file (ignored).
Malformed input raises InputError naming the file and the line.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from fpe_jax.errors import InputError

TABLE_SUFFIXES = (".csv", ".txt")

# Accepted spellings of the columns we look for (lower case).
T_NAMES = ("t", "t_s", "time", "stamp", "timestamp")
X_NAMES = ("x", "x_m")
Y_NAMES = ("y", "y_m")
YAW_NAMES = ("yaw", "yaw_rad", "psi", "psi_rad")
SPEED_NAMES = ("v", "v_mps", "speed", "speed_mps", "vx_mps")


@dataclasses.dataclass(frozen=True)
class Table:
    """A parsed table: data (rows, cols) float64, header lower-cased names or None."""

    source: Path
    data: np.ndarray
    header: tuple[str, ...] | None

    def column(self, names: tuple[str, ...], what: str, required: bool = True) -> np.ndarray | None:
        """The (rows,) column whose header is one of `names`; None (or InputError) if absent."""
        if self.header is not None:
            for name in names:
                if name in self.header:
                    return self.data[:, self.header.index(name)]
        if required:
            raise InputError(
                self.source,
                f"no {what} column in header {','.join(self.header or ())!r}",
                f"a column named {' or '.join(names)}",
            )
        return None


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _splitter(line: str):
    if ";" in line:
        return lambda s: [c.strip() for c in s.split(";")]
    if "," in line:
        return lambda s: [c.strip() for c in s.split(",")]
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
            rows.append([float(c) for c in cells])
        except ValueError:
            bad = next(c for c in cells if not _is_number(c))
            raise InputError(p, f"line {i + 1}: non-numeric cell {bad!r}", "numbers") from None
    if not rows:
        raise InputError(p, "has a header but no data rows", "a table of numbers")
    if header is not None:
        # Names like "x [m]" are common in hand-made files; keep the bare name.
        header = tuple(re.sub(r"\s*[\[(].*$", "", h).strip() for h in header)
        if len(set(header)) != len(header):
            raise InputError(p, f"repeated column names in header {','.join(header)!r}")
    return Table(p, np.asarray(rows, dtype=np.float64), header)
