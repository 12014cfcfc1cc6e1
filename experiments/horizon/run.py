"""Error against the prediction horizon, 0.1-5 s: the fitted predictor against every baseline.

The cases and predictors of the approaches study (experiments/approaches/run.py: the real Levine
lap, fit on its first 60 % and scored on the rest; the built-in oval and hairpin and the five
F1TENTH tracks, a 60 s fit drive and a separate 40 s test drive each), on a 50-step grid of
0.1 s: the fit itself is made on that grid (`fpe fit --horizon 50`), and every preset is scored
on it, with the line model's pace return free (`--fit delay,tau,pace,smoothing,filter`). The
thesis's blend is `seed` (the 0.7 blend as the 2019 node ran it) and `seed-measured-speed`.

The line model's state estimator (`fpe fit --estimator`: the Kalman filter or the Theil-Sen
lines) is chosen per case as a user would choose it, on the fit drive alone: each is fitted on
its first 70 % and scored on the rest (the geometric mean over the lead times of the mean error:
every lead time alike, as the long-horizon fit weighs them), and the better one is fitted on the
whole fit drive.

Why it matters at 0.1 s on the Levine lap: about half its rows repeat the last detection (none
came) and are predicted from as if fresh. From those the first step misses by ~0.24 m, from
fresh rows by ~0.06 m, and one delay serves both: the stale rows ask for more of it. The Kalman
fit's 0.028 s moved the fresh rows' first step too far (there ctrv, without delay, was 6 mm
closer) and tied ctrv at 0.1 s (0.04 mm behind); the Theil-Sen fit (0.023 s) is ahead at every
step. Tried on the Levine lap and not kept: weighing the steps by the fitted model's own errors
(more weight on 0.1 s: the delay rose, 0.1 s 0.2 mm worse); the Huber threshold as a fixed
multiple of each step's typical error (0.1 s 0.2 mm better, 1 s and 5 s worse); advancing a
repeated row by its age (0.1 s 26 mm better, 1 s and 5 s 5 % worse; rows one repeat old were
predicted worse advanced: the stamps are the logger's, not the detector's).

Acceptance: on every simulated track the fitted mean error at 3 s and at 5 s is at most 0.5x the
best baseline's; on Levine the fitted error is below every baseline's at every step.

Run:  .venv/bin/python experiments/horizon/run.py [CASE ...]   (about 17 minutes on the 2-core
machine; naming cases, e.g. Levine, runs only those and prints their summary)
Writes experiments/results/horizon.md and experiments/results/horizon.png.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import jax
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "approaches"))
import run as approaches  # noqa: E402  (the approaches study: its predictors and tables)

from fpe_jax import plots  # noqa: E402
from fpe_jax.evaluate._evaluate import split_drive  # noqa: E402
from fpe_jax.fit._cases import fit_case, study_cases  # noqa: E402
from fpe_jax.model._params import presets, with_settings  # noqa: E402
from fpe_jax.progress import Progress  # noqa: E402

RESULTS = approaches.RESULTS
DATA = approaches.DATA
HORIZON = 50  # steps of 0.1 s: 5 s, what planners read
MARKS_S = (1.0, 3.0, 5.0)  # the horizons the summary reports
RATIO_AT_S = (3.0, 5.0)  # where the fitted error must be <= 0.5x the best baseline's
BASELINES = tuple(n for n in approaches.ORDER if n != "fitted")
# the line model's default groups and "pace": its pace's return to the learned speed profile,
# which carries the tail of a 5 s horizon on drives whose pace the profile was learned from
# (not `fpe fit`'s default, which must also follow a car that changed its pace)
FREE = ("delay", "tau", "pace", "smoothing", "filter")
# the groups with each estimator (the filter's noise values exist only with the filter)
FREE_BY_ESTIMATOR = {"kalman": FREE, "theil-sen": tuple(g for g in FREE if g != "filter")}
INNER_HOLDOUT = 0.3  # share of the fit drive (its end) that scores the estimators


def at(report: dict, name: str, t_s: float, dt_s: float) -> float:
    """Mean error [m] of a predictor at lead time t_s."""
    return float(report[name]["per_step_m"][int(round(t_s / dt_s)) - 1])


def best_baseline(report: dict, t_s: float, dt_s: float) -> tuple[str, float]:
    return min(((n, at(report, n, t_s, dt_s)) for n in BASELINES), key=lambda p: p[1])


def inner_scores(case, init, say) -> dict[str, float]:
    """Estimator -> the geometric mean over lead times of the mean error [m] of the line model
    fitted with it on the first 1 - INNER_HOLDOUT of the case's fit drive, on the rest."""
    inner, val = split_drive(case.fit_drive, INNER_HOLDOUT)
    part = dataclasses.replace(case, fit_drive=inner, test_drive=val)
    out = {}
    for est, free in FREE_BY_ESTIMATOR.items():
        say(f"{case.name}: scoring the {est} estimator on the fit drive's inner split")
        res = fit_case(part, model=approaches.MODEL, fit=free, init=init, estimator=est)
        per = np.asarray(res.report["fitted"]["per_step_m"], dtype=np.float64)
        out[est] = float(np.exp(np.nanmean(np.log(per))))
    return out


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    init = with_settings(presets["default"], horizon=HORIZON)
    only = set(sys.argv[1:])
    results = []
    with Progress() as say:
        say("simulating the drives and reading the Levine lap")
        todo = [c for c in study_cases(DATA, say) if not only or c.name in only]
        if only - {c.name for c in todo}:
            raise SystemExit(f"unknown case(s): {', '.join(sorted(only - {c.name for c in todo}))}")
        for i, case in enumerate(todo):
            scores = inner_scores(case, init, say)
            est = min(scores, key=scores.get)
            say(f"[{i + 1}/{len(todo)}] {case.name}: fitting ({est}) on the {HORIZON}-step grid")
            res = fit_case(
                case,
                model=approaches.MODEL,
                blend="auto",
                fit=FREE_BY_ESTIMATOR[est],
                init=init,
                estimator=est,
                progress=lambda m, n=case.name: say(f"{n}: {m}"),
            )
            results.append((case, res, est, scores))
    dt_s = results[0][1].params.settings.dt_s
    if only:  # a partial run: its summary, nothing written
        print(markdown(results, dt_s, time.perf_counter() - t0, "-").split("## Mean")[0])
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    fig = plots.error_vs_horizon_figure(
        {c.name + (" (sim)" if c.latency_s else " (real)"): r.report for c, r, *_ in results},
        dt_s=dt_s,
        names=approaches.ORDER,
        title="Mean position error vs horizon (0.1-5 s) on held-out data",
    )
    png = plots.save(fig, RESULTS / "horizon.png")
    md = RESULTS / "horizon.md"
    md.write_text(markdown(results, dt_s, time.perf_counter() - t0, png.name))
    print(f"wrote {md} and {png}")


def markdown(results, dt_s: float, wall_s: float, png: str) -> str:
    marks = " | ".join(f"fitted {t:g} s | best baseline {t:g} s | ratio" for t in MARKS_S)
    lines = [
        "# Error against the horizon, 0.1-5 s",
        "",
        f"Regenerate: `.venv/bin/python experiments/horizon/run.py` (this run: "
        f"{wall_s / 60:.1f} min wall on the shared 2-core machine).",
        "",
        "The approaches study's cases and predictors (experiments/results/approaches.md) on a "
        f"{HORIZON}-step grid of {dt_s:g} s: the fitted predictor (`fpe fit --horizon "
        f"{HORIZON} --fit {','.join(FREE)}`, the line model with its pace's return to the "
        "speed profile; `filter` only with the Kalman estimator) is fitted on that grid and "
        "every preset is scored on it, "
        "on data the fit did not see (Levine: the last 40 % of the lap; simulated: a separate "
        "40 s drive, latency 0.3 s, targets the true positions). Errors are means over the "
        "held-out predictions at each lead time. The thesis's blend is `seed` (and "
        "`seed-measured-speed`).",
        "",
        "The line model's state estimator (`--estimator kalman` or `theil-sen`) is chosen per "
        f"case on the fit drive alone: each is fitted on its first {1 - INNER_HOLDOUT:.0%} and "
        f"scored on the last {INNER_HOLDOUT:.0%} by the geometric mean over the lead times of "
        "the mean error (every lead time alike); the better one is fitted on the whole fit "
        "drive ('estimator' below, with both inner scores [m]).",
        "",
        f"![error vs horizon]({png})",
        "",
        "## Summary",
        "",
        "Ratio = fitted / best baseline at that lead time (simulated tracks: <= 0.5 asked at 3 s "
        "and 5 s). 'Beaten at' lists every baseline@step where a baseline's error is below the "
        "fitted one, and by how much (Levine: none asked).",
        "",
        f"| case | {marks} | meets the target | beaten at | estimator (inner: kalman, theil-sen) |",
        "|---" * (2 + 3 * len(MARKS_S) + 2) + "|",
    ]
    for case, r, est, scores in results:
        rep = r.report
        cells = []
        for t in MARKS_S:
            name, best = best_baseline(rep, t, dt_s)
            fit = at(rep, "fitted", t, dt_s)
            cells.append(f"{fit:.3f} | {best:.3f} ({name}) | {fit / best:.2f}")
        fitted = np.asarray(rep["fitted"]["per_step_m"])
        beaten = [
            f"{n}@{k + 1} (-{1000 * (fitted[k] - rep[n]['per_step_m'][k]):.2f} mm)"
            for n in BASELINES
            for k in np.flatnonzero(np.asarray(rep[n]["per_step_m"]) < fitted)
        ]
        if case.latency_s is None:
            ok = not beaten
        else:
            ok = all(
                at(rep, "fitted", t, dt_s) <= 0.5 * best_baseline(rep, t, dt_s)[1]
                for t in RATIO_AT_S
            )
        shown = ", ".join(beaten[:6]) + (f" (+{len(beaten) - 6})" if len(beaten) > 6 else "")
        inner = ", ".join(f"{scores[e]:.3f}" for e in FREE_BY_ESTIMATOR)
        lines.append(
            f"| {case.name} | {' | '.join(cells)} | {'yes' if ok else 'NO'} | {shown or 'none'} "
            f"| {est} ({inner}) |"
        )
    lines += ["", "## Mean error [m] at each second", ""]
    steps = [int(round(t / dt_s)) - 1 for t in (0.5, 1.0, 2.0, 3.0, 4.0, 5.0)]
    for case, r, *_ in results:
        rep = r.report
        lines += [
            f"### {case.name}",
            "",
            "| predictor | " + " | ".join(f"{(k + 1) * dt_s:.1f} s" for k in steps) + " |",
            "|---" * (len(steps) + 1) + "|",
        ]
        for name in approaches.ORDER:
            per = rep[name]["per_step_m"]
            label = plots.APPROACH[name]
            lines.append(f"| {label} | " + " | ".join(f"{per[k]:.3f}" for k in steps) + " |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
