"""`fpe demo` and the pieces the experiments share: fit/test cases, fitting one, its predictions.

A `Case` is one honest fit-and-test problem: the waypoints the predictors get, a drive to fit on
and a different drive (or the later part of the same one) to report on. `simulated_case` makes one
from the simulator (two drives with different seeds: different start, line, noise), `levine_case`
from the real 2019 lap (a temporal split), `f1tenth_cases` for the five F1TENTH tracks.

`run_demo` is the whole product on the embedded default data, on a machine with no data: simulate,
fit, compare with every preset on the test drive, check the claims, write plots and the config.
Not a core module: it may write files and (lazily) import matplotlib through `fpe_jax.plots`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from fpe_jax.drive import Drive
from fpe_jax.errors import InputError

LATENCY_S = 0.3  # the thesis measured ~0.4 s of AprilTag delay; the simulator's default is 0.3
F1TENTH_TRACKS = ("Austin", "Catalunya", "Monza", "Silverstone", "Spielberg")

# The demo: a short fit drive and a separate, shorter test drive on the built-in oval. Seeds are
# fixed so that the printed numbers are reproducible; the checks below hold for them (and were
# checked on other seeds, see experiments/weights for the latency sweep).
DEMO_TRACK = "oval"
DEMO_FIT_S, DEMO_TEST_S = 40.0, 30.0
DEMO_FIT_SEED, DEMO_TEST_SEED = 1, 2
DEMO_BLEND = "position"  # one solve; "auto" would fit both modes first (3 solves, ~2x the time)
DELAY_TOLERANCE_S = 0.05


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
        from fpe_jax.track import Track

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
    from fpe_jax.sim import simulate

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
    from fpe_jax.evaluate import split_drive

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


def study_cases(data_dir: str | Path, say: Callable[[str], None] = lambda msg: None) -> list[Case]:
    """The cases the comparison studies share: the real Levine lap (fit 60 %, test 40 %) when
    `data_dir` has it, the built-in oval and hairpin, and the F1TENTH tracks when present. The
    simulated drives have LATENCY_S of detection latency; `say` is told what is left out."""
    data = Path(data_dir)
    out = []
    if (data / "levine").is_dir():
        out.append(levine_case(data, holdout=0.4))
    else:
        say(f"note: {data / 'levine'} not found; the real-data part is left out")
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
    progress: Callable[[str], None] = lambda msg: None,
):
    """Fit on the case's fit drive and report on its test drive -> `fpe_jax.fit.FitResult`.

    model, blend: as `fpe_jax.fit.fit` takes them (default: the line model)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from fpe_jax.fit import fit as fit_drives

    track = case.track()
    return fit_drives(
        [case.fit_drive],
        [track],
        free=tuple(fit) if fit else None,
        model=model,
        blend=blend,
        test_drives=[case.test_drive],
        test_tracks=[track],
        progress=progress,
    )


def fde_ratio(report: dict, baseline: str = "seed-measured-speed") -> float:
    """Fitted FDE over a baseline's FDE on the same held-out data (< 1: the fit is better)."""
    return report["fitted"]["fde_m"] / report[baseline]["fde_m"]


def presets_beating_fitted(report: dict) -> list[str]:
    """'name@step' for every preset whose mean error beats the fitted one at some step."""
    fitted = np.asarray(report["fitted"]["per_step_m"])
    out = []
    for name, m in report.items():
        if name == "fitted":
            continue
        better = np.flatnonzero(np.asarray(m["per_step_m"]) < fitted)
        out += [f"{name}@{k + 1}" for k in better]
    return out


# ---- the demo ------------------------------------------------------------------------------------


@dataclasses.dataclass
class DemoResult:
    """What `run_demo` did: the case, the fit, the checks and the files written.

    Attributes:
        case: the simulated fit/test drives.
        result: the `FitResult` (params, uncertainty, held-out report of fitted + presets).
        checks: (claim, passed, detail) for each claim the demo makes.
        files: paths written.
        seconds: wall time of the whole demo [s].
    """

    case: Case
    result: object
    checks: list[tuple[str, bool, str]]
    files: list[Path]
    seconds: float


def demo_checks(result, latency_s: float) -> list[tuple[str, bool, str]]:
    """The demo's claims: the fit beats the seed on the test drive and recovers the latency."""
    rep = result.report
    delay = result.params.physical()["delay_s"]
    f, s = rep["fitted"], rep["seed"]
    return [
        (
            "fitted beats seed on the test drive (ADE and FDE)",
            f["ade_m"] < s["ade_m"] and f["fde_m"] < s["fde_m"],
            f"ADE {f['ade_m']:.3f} vs {s['ade_m']:.3f} m, "
            f"FDE {f['fde_m']:.3f} vs {s['fde_m']:.3f} m",
        ),
        (
            f"fitted delay within {DELAY_TOLERANCE_S} s of the true latency",
            abs(delay - latency_s) <= DELAY_TOLERANCE_S,
            f"delay {delay:.3f} s vs latency {latency_s:.3f} s (error {delay - latency_s:+.3f} s)",
        ),
    ]


def run_demo(
    out_dir: str | Path,
    *,
    track: str = DEMO_TRACK,
    fit_s: float = DEMO_FIT_S,
    test_s: float = DEMO_TEST_S,
    latency_s: float = LATENCY_S,
    fit_seed: int = DEMO_FIT_SEED,
    test_seed: int = DEMO_TEST_SEED,
    blend: str = DEMO_BLEND,
    progress: Callable[[str], None] = lambda msg: None,
    force: bool = False,
) -> DemoResult:
    """Simulate, fit, evaluate against every preset, check, plot and export into `out_dir`.

    Files (DEMO_FILES; existing ones are replaced only with `force`, checked before any work):
    config.json (the tuned config), params.yaml (ROS 2 parameters), waypoints.csv (the
    centerline, x,y [m]), trajectory.png, error_vs_horizon.png, line.png (weights.png for the
    blend model), report.md (the table and the checks).
    """
    from fpe_jax.io.writers import check_output_paths

    t0 = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "is not a folder", "a folder for the demo's plots and config")
    if not out.exists():
        # the outermost missing folder: its parent exists and is writable (`out/demo` on a
        # fresh checkout has neither folder)
        first_missing = next(p for p in (out, *out.parents) if p.parent.exists())
        check_output_paths([first_missing], force)
        out.mkdir(parents=True)
    check_output_paths([out / name for name in DEMO_FILES], force)
    progress(f"simulating a {fit_s:g} s fit drive and a {test_s:g} s test drive on '{track}'")
    case = simulated_case(
        track,
        fit_s=fit_s,
        test_s=test_s,
        latency_s=latency_s,
        fit_seed=fit_seed,
        test_seed=test_seed,
    )
    result = fit_case(case, blend=blend, progress=progress)
    checks = demo_checks(result, latency_s)
    files = write_demo_outputs(out, case, result, checks, progress, force)
    return DemoResult(case, result, checks, files, time.perf_counter() - t0)


DEMO_FILES = (
    "waypoints.csv",
    "config.json",
    "params.yaml",
    "trajectory.png",
    "error_vs_horizon.png",
    "line.png",
    "report.md",
)


def write_demo_outputs(
    out: Path, case: Case, result, checks, progress, force: bool = False
) -> list[Path]:
    """Config, ROS 2 parameters, waypoints, plots and report.md of a finished demo fit."""
    from fpe_jax import plots
    from fpe_jax.config import params_to_config, write_config
    from fpe_jax.evaluate import heldout_predictions
    from fpe_jax.export import export_config
    from fpe_jax.io.writers import write_text, write_xy_csv
    from fpe_jax.params import presets
    from fpe_jax.report import provenance

    progress("writing the tuned config and the ROS 2 parameters")
    # every digit: a line-model config is tied to the exact waypoint values (sha256)
    waypoints = write_xy_csv(out / "waypoints.csv", case.waypoints_xy_m, fmt="%.17g", force=force)
    cfg_path = out / "config.json"
    sources = [f"fit:{case.description}", f"test:{case.description}"]
    cfg = params_to_config(
        result.params,
        uncertainty=result.uncertainty,
        provenance=provenance(result, sources, {"pose": None, "truth": None}),
        line=_line_section(result, waypoints),
    )
    write_config(cfg_path, cfg, force=force)
    files = [waypoints, cfg_path]
    files += export_config(cfg_path, "ros2", out / "params.yaml", waypoints=waypoints, force=force)

    progress("predicting the test drive for the plots")
    track = case.track()
    names = ("seed", "seed-measured-speed", "frenet", "fitted")
    by_name = {n: presets[n] for n in names[:-1]} | {"fitted": result.params}
    held = heldout_predictions(case.test_drive, track, by_name)
    dt_s = result.params.settings.dt_s
    last = "line.png" if result.params.settings.model == "line" else "weights.png"
    progress(f"drawing trajectory.png, error_vs_horizon.png, {last}")
    fig = plots.trajectory_figure(
        case.waypoints_xy_m,
        case.test_drive,
        held,
        names=names,
        half_width_m=case.half_width_m,
        corner_by="seed-measured-speed",
        title=f"Demo: 1 s predictions on the test drive ({case.name}, latency "
        f"{case.latency_s:g} s); zoom where the hand-set blend turns earliest",
    )
    files.append(plots.save(fig, out / "trajectory.png", force=force))
    fig = plots.error_vs_horizon_figure(
        {case.name: result.report},
        dt_s=dt_s,
        title=f"Demo: mean error vs horizon on the test drive ({case.name})",
    )
    files.append(plots.save(fig, out / "error_vs_horizon.png", force=force))
    if last == "line.png":
        fig = plots.line_figure(
            result.params,
            float(track.length_m),
            track.closed,
            title=f"Demo: the line and speed profile learned from the fit drive ({case.name})",
        )
    else:
        fig = plots.weights_figure(
            {f"fitted on {case.name} ({result.info['blend']} blend)": result.params},
            title="Demo: fitted per-step weights vs the thesis's 0.7^i",
            latency_s=case.latency_s,
        )
    files.append(plots.save(fig, out / last, force=force))
    report = out / "report.md"
    write_text(report, demo_report(case, result, checks), force=force)
    files.append(report)
    return files


def _line_section(result, waypoints: Path) -> dict | None:
    """The config's `line` section for a line-model fit (None for other models)."""
    sha = result.info.get("waypoints_sha256")
    return None if sha is None else {"waypoints_sha256": sha, "waypoints": str(waypoints)}


def demo_report(case: Case, result, checks) -> str:
    """The demo's Markdown report: what was run, the fitted values, the table, the checks."""
    from fpe_jax.report import format_fitted, format_table

    p = result.params.physical()
    if result.params.settings.model == "line":
        fitted = [format_fitted(result), f"true latency {case.latency_s:.3f} s"]
    else:
        fitted = [
            f"fitted ({result.info['blend']} blend, {result.info['steps']} solver steps): "
            f"lookahead {p['lookahead_m']:.3f} m + {p['lookahead_gain_s']:.3f} s * v, "
            f"delay {p['delay_s']:.3f} s (true latency {case.latency_s:.3f} s), "
            f"speed {p['speed_weight']:.2f} * measured + {1 - p['speed_weight']:.2f} * "
            f"{p['speed_mps']:.2f} m/s",
            "",
            "weights " + " ".join(f"{w:.3f}" for w in p["weights"]),
        ]
    lines = [
        f"# fpe demo: {case.description}",
        "",
        *fitted,
        "",
        "Held-out (the separate test drive):",
        "",
        format_table(result.report),
        "",
    ]
    lines += [f"- {'PASS' if ok else 'FAIL'}: {claim}: {detail}" for claim, ok, detail in checks]
    return "\n".join(lines) + "\n"
