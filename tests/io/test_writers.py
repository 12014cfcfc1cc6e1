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
