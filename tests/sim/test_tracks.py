"""`fpe simulate` applies the track checks of the other commands before simulating: a track too
small or too large, a far spike and a loop tighter than the car's turning circle are one-line
errors (exit 2), quickly, and the built-in and real tracks still simulate."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from fpe_jax.cli import main
from fpe_jax.errors import InputError
from fpe_jax.sim._sim import Vehicle, check_drivable, simulate

DATA = Path(__file__).resolve().parents[2] / "data"
SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


def _circle(radius_m: float, n: int = 60) -> np.ndarray:
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return radius_m * np.stack([np.cos(a), np.sin(a)], axis=1)


def _spike(km: float) -> np.ndarray:
    oval = np.loadtxt(DATA / "tracks" / "oval.csv", delimiter=",", skiprows=1)[:, :2]
    return np.insert(oval, 10, oval[10] + [km * 1000.0, 0.0], axis=0)


BAD = {
    "tiny": (_circle(1e-4), "m long"),
    "huge": (_circle(1e6), "m long"),
    "spike-283km": (_spike(283.0), "m long"),
    "tighter-than-the-car": (_circle(0.5), "turning"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_simulate_refuses_tracks_it_cannot_drive(tmp_path, capsys, case):
    xy, words = BAD[case]
    track = tmp_path / f"{case}.csv"
    np.savetxt(track, xy, delimiter=",", header="x,y", comments="", fmt="%.17g")
    t0 = time.perf_counter()
    rc = main(["simulate", "--track", str(track), "--duration", "20", "--out", str(tmp_path / "o")])
    took_s = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert str(track) in err and words in err
    assert took_s < 5.0
    assert not (tmp_path / "o").exists()


def test_the_turning_rule_is_the_car_s_turning_circle(tmp_path):
    car = Vehicle()
    r_min = (car.lf_m + car.lr_m) / np.tan(car.steer_max_rad)
    check_drivable(_circle(1.05 * r_min), car, "ok")
    with pytest.raises(InputError, match="turning"):
        check_drivable(_circle(0.95 * r_min), car, "tight")
    with pytest.raises(InputError, match="turning"):  # the raceline is checked the same way
        raceline = tmp_path / "tight.csv"
        np.savetxt(raceline, _circle(0.95 * r_min), delimiter=",", header="x,y", comments="")
        simulate("oval", duration_s=1.0, raceline=raceline)


@pytest.mark.parametrize("name", ["oval", "hairpin", "random:3"])
def test_builtin_tracks_pass(name):
    from fpe_jax.sim._sim import builtin_track

    check_drivable(builtin_track(name)[0], Vehicle(), name)


def test_real_tracks_pass():
    files = sorted(SHARED.glob("tracks/*.csv")) + sorted(SHARED.glob("levine/*waypoints*.csv"))
    if not files:
        pytest.skip(f"no real tracks under {SHARED}")
    from fpe_jax.io import load_waypoints

    for f in files:
        check_drivable(load_waypoints(f).xy_m, Vehicle(), str(f))
