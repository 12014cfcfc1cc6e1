"""Prediction CSVs: the text np.savetxt writes for the same columns and formats, to the byte."""

from __future__ import annotations

import numpy as np
import pytest

from fpe_jax.io.writers import write_predictions


def _savetxt_reference(path, stamps_s, poses, dt_s, cov_m2, valid):
    n, h = poses.shape[:2]
    step = np.tile(np.arange(1, h + 1), n)
    cols = [np.repeat(stamps_s, h), step, step * float(dt_s), poses.reshape(n * h, 3)]
    fmt = ["%.9f", "%d", "%.9f", "%.9f", "%.9f", "%.9f"]
    header = "stamp,step,horizon_s,x,y,yaw"
    if cov_m2 is not None:
        c = cov_m2.reshape(n * h, 2, 2)
        cols += [c[:, 0, 0], c[:, 0, 1], c[:, 1, 1]]
        fmt += ["%.9g"] * 3
        header += ",cov_xx_m2,cov_xy_m2,cov_yy_m2"
    if valid is not None:
        cols.append(np.repeat(valid.astype(np.int64), h))
        fmt.append("%d")
        header += ",valid"
    with open(path, "x", newline="") as f:
        np.savetxt(f, np.column_stack(cols), fmt=fmt, delimiter=",", header=header, comments="")


@pytest.mark.parametrize("extras", ["none", "cov", "valid", "both"])
def test_prediction_csv_is_what_savetxt_writes(tmp_path, extras):
    rng = np.random.default_rng(7)
    n, h = 37, 10
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.01, 0.2, n))  # epoch stamps: all digits kept
    poses = rng.normal(0.0, 1e3, (n, h, 3)) * rng.choice([1e-12, 1.0, 1e6], (n, h, 3))
    poses[0, 0] = [-0.0, 1e-300, -1e300]
    cov = rng.normal(0.0, 1.0, (n, h, 2, 2)) ** 2 * 10.0 ** rng.integers(-20, 20, (n, h, 1, 1))
    cov[1] = np.nan  # a prediction without an ellipse
    cov[2, 0, 0, 0] = np.inf
    valid = rng.integers(0, 2, n).astype(bool)
    cov_m2 = cov if extras in ("cov", "both") else None
    ok = valid if extras in ("valid", "both") else None
    write_predictions(tmp_path / "p.csv", stamps, poses, 0.1, cov_m2=cov_m2, valid=ok)
    _savetxt_reference(tmp_path / "ref.csv", stamps, poses, 0.1, cov_m2, ok)
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "ref.csv").read_bytes()


def test_a_long_prediction_csv_is_written_in_blocks_of_bounded_memory(tmp_path, monkeypatch):
    """The text goes out a block of rows at a time: the memory the writer holds does not grow
    with the log (`fpe predict` of the hostile study's 300,000-row log), and the blocks join to
    savetxt's text, a partial last block included."""
    import tracemalloc

    import fpe_jax.io.writers as W

    rng = np.random.default_rng(3)
    n, h = 2_000, 10  # 20,000 rows, 20 blocks: held whole they would exceed the limit
    stamps, poses = np.arange(n) * 0.05, rng.normal(0.0, 10.0, (n, h, 3))
    monkeypatch.setattr(W, "CSV_BLOCK_ROWS", 1_000)
    tracemalloc.start()
    write_predictions(tmp_path / "long.csv", stamps, poses, 0.1)
    peak_b = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak_b < 1e6, peak_b  # a block of 1,000 rows: ~0.35 MB
    _savetxt_reference(tmp_path / "ref.csv", stamps, poses, 0.1, None, None)
    assert (tmp_path / "long.csv").read_bytes() == (tmp_path / "ref.csv").read_bytes()
    monkeypatch.setattr(W, "CSV_BLOCK_ROWS", 40)  # 4 observations of 10 steps
    cov, valid = rng.uniform(0.0, 1.0, (37, h, 2, 2)), rng.integers(0, 2, 37).astype(bool)
    write_predictions(tmp_path / "p.csv", stamps[:37], poses[:37], 0.1, cov_m2=cov, valid=valid)
    _savetxt_reference(tmp_path / "r.csv", stamps[:37], poses[:37], 0.1, cov, valid)
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "r.csv").read_bytes()
