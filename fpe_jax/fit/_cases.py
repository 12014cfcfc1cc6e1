"""The study cases: honest fit-and-test problems the demo and the experiments share.

A `Case` is one honest fit-and-test problem: the waypoints the predictors get, a drive to fit on
and a different drive (or the later part of the same one) to report on. `simulated_case` makes one
from the simulator (two drives with different seeds: different start, line, noise), `levine_case`
from the real 2019 lap (a temporal split), `f1tenth_cases` for the five F1TENTH tracks;
`fit_case` fits one and reports on its test drive.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fpe_jax.drive import Drive

LATENCY_S = 0.3  # the thesis measured ~0.4 s of AprilTag delay; the simulator's default is 0.3
F1TENTH_TRACKS = ("Austin", "Catalunya", "Monza", "Silverstone", "Spielberg")
DELAY_TOLERANCE_S = 0.05  # how close a fitted delay must come to the true latency [s]


@dataclasses.dataclass(frozen=True)
class Case:
    """One fit/test problem.

    Attributes:
        name: short label for tables and plots.
        waypoints_xy_m: (K, 2) the path the predictors are given (centerline) [m].
        fit_drive: the drive the parameters are fitted on.
        test_drive: the drive the report is made on (never seen by the fit).
        latency_s: true detection latency [s] for simulated drives; None for real ones.
        half_width_m: track half-width [m] for drawing the edges; None when unknown.
        description: where the drives came from (for provenance and captions).
    """

    name: str
    waypoints_xy_m: np.ndarray
    fit_drive: Drive
    test_drive: Drive
    latency_s: float | None
    half_width_m: float | None
    description: str

    def track(self):
        """The `Track` built from the waypoints (JAX)."""
        from fpe_jax.geometry._track import Track

        return Track.from_waypoints(self.waypoints_xy_m)


def simulated_case(
    track: str | Path,
    *,
    name: str | None = None,
    raceline: str | Path | None = None,
    fit_s: float = 60.0,
    test_s: float = 40.0,
    latency_s: float = LATENCY_S,
    fit_seed: int = 1,
    test_seed: int = 2,
) -> Case:
    """A fit drive and a separate test drive on one track (different seeds), both simulated.

    Args:
        track: built-in name (oval, hairpin, random:SEED) or a centerline file.
        raceline: optional raceline file the simulated driver follows (predictors still get the
            centerline, as a team would).
        fit_s, test_s: drive durations [s].
        latency_s: detection latency [s] of both drives.
        fit_seed, test_seed: simulator seeds of the two drives.
    """
    from fpe_jax.sim._sim import simulate

    kw = dict(latency_s=latency_s, raceline=raceline)
    fit_res = simulate(track, duration_s=fit_s, seed=fit_seed, **kw)
    test_res = simulate(track, duration_s=test_s, seed=test_seed, **kw)
    label = name or fit_res.scenario["track"]
    return Case(
        name=label,
        waypoints_xy_m=fit_res.centerline_xy_m,
        fit_drive=fit_res.drive,
        test_drive=test_res.drive,
        latency_s=float(latency_s),
        half_width_m=float(fit_res.half_width_m),
        description=(
            f"simulated {label}: fit {fit_s:g} s (seed {fit_seed}), test {test_s:g} s "
            f"(seed {test_seed}), latency {latency_s:g} s"
            + (", driver on the raceline" if raceline is not None else "")
        ),
    )


def f1tenth_cases(tracks_dir: str | Path, **kw) -> list[Case]:
    """One `simulated_case` per F1TENTH track in `tracks_dir` (NAME_centerline.csv as the
    predictors' path, NAME_raceline.csv as the driver's line); keyword options as there."""
    d = Path(tracks_dir)
    return [
        simulated_case(d / f"{n}_centerline.csv", name=n, raceline=d / f"{n}_raceline.csv", **kw)
        for n in F1TENTH_TRACKS
    ]


def levine_case(data_dir: str | Path, *, holdout: float = 0.4) -> Case:
    """The real 2019 Levine lap (10 Hz, no yaw): fit on the first 1 - holdout, test on the rest.

    Args:
        data_dir: the shared data folder (holding levine/actual-poses.csv and the waypoints).
        holdout: fraction of the drive's duration held out at its end.
    """
    from fpe_jax import io
    from fpe_jax.evaluate._evaluate import split_drive

    lev = Path(data_dir) / "levine"
    drive = io.load_drive(lev / "actual-poses.csv", rate_hz=10.0)
    train, test = split_drive(drive, holdout)
    return Case(
        name="Levine",
        waypoints_xy_m=io.load_waypoints(lev / "levine-waypoints.csv").xy_m,
        fit_drive=train,
        test_drive=test,
        latency_s=None,
        half_width_m=None,
        description=(
            f"real Levine lap (AprilTag trace, 10 Hz): fit first {1 - holdout:.0%}, "
            f"test last {holdout:.0%}"
        ),
    )


# the comparison studies' drives: a 60 s fit drive and a separate 40 s test drive per track
STUDY_FIT_S, STUDY_TEST_S, STUDY_FIT_SEED, STUDY_TEST_SEED = 60.0, 40.0, 1, 2


def real_cases(data_dir: str | Path, say: Callable[[str], None] = lambda msg: None) -> list[Case]:
    """[the real Levine lap (fit 60 %, test 40 %)] when `data_dir` has it, else [] and a note."""
    if (Path(data_dir) / "levine").is_dir():
        return [levine_case(data_dir, holdout=0.4)]
    say(f"note: {Path(data_dir) / 'levine'} not found; the real-data part is left out")
    return []


def study_cases(data_dir: str | Path, say: Callable[[str], None] = lambda msg: None) -> list[Case]:
    """The cases the comparison studies share: the real Levine lap (fit 60 %, test 40 %) when
    `data_dir` has it, the built-in oval and hairpin, and the F1TENTH tracks when present. The
    simulated drives have LATENCY_S of detection latency; `say` is told what is left out."""
    data = Path(data_dir)
    out = real_cases(data, say)
    kw = dict(
        fit_s=STUDY_FIT_S,
        test_s=STUDY_TEST_S,
        latency_s=LATENCY_S,
        fit_seed=STUDY_FIT_SEED,
        test_seed=STUDY_TEST_SEED,
    )
    out += [simulated_case(track, **kw) for track in ("oval", "hairpin")]
    if (data / "tracks").is_dir():
        out += f1tenth_cases(data / "tracks", **kw)
    else:
        say(f"note: {data / 'tracks'} not found; the F1TENTH tracks are left out")
    return out


def fit_case(
    case: Case,
    *,
    blend: str = "position",
    fit: Sequence[str] | None = None,
    model: str = "line",
    init=None,
    estimator: str | None = None,
    progress: Callable[[str], None] = lambda msg: None,
):
    """Fit on the case's fit drive and report on its test drive -> `fpe_jax.fit.FitResult`.

    model, blend, init, estimator: as `fpe_jax.fit.fit` takes them (default: the line model
    with `fit`'s default estimator; init's
    prediction grid, e.g. a 50-step horizon, is the fit's and the report's); needs float64 as
    `fit` does (the caller enables jax_enable_x64 at start-up)."""
    from fpe_jax.fit._fit import fit as fit_drives

    track = case.track()
    kw = {} if estimator is None else {"estimator": estimator}
    return fit_drives(
        [case.fit_drive],
        [track],
        free=tuple(fit) if fit else None,
        model=model,
        blend=blend,
        test_drives=[case.test_drive],
        test_tracks=[track],
        init=init,
        progress=progress,
        **kw,
    )


def fde_ratio(report: dict, baseline: str = "seed-measured-speed") -> float:
    """Fitted FDE over a baseline's FDE on the same held-out data (< 1: the fit is better)."""
    return report["fitted"]["fde_m"] / report[baseline]["fde_m"]


def presets_beating_fitted(report: dict) -> list[str]:
    """'name@step' for every preset whose mean error beats the fitted one at some step."""
    fitted = np.asarray(report["fitted"]["per_step_m"])
    return [
        f"{name}@{k + 1}"
        for name, m in report.items()
        if name != "fitted"
        for k in np.flatnonzero(np.asarray(m["per_step_m"]) < fitted)
    ]
