"""The thesis's approaches 1-4 against the fitted predictor, on the real Levine lap and on
simulated drives (built-in oval and hairpin, the five F1TENTH tracks).

Approach 1 (displacement) = the `constant-velocity` preset, 2 = `linear`, 3 = `pure-pursuit`,
4 = `seed` (the 0.7 blend exactly as the 2019 node ran it, speed hard-coded to 1 m/s) and
`seed-measured-speed` (the same rules with the measured speed); `ctrv` and `frenet` (along-track
speed held, lateral offset decaying to the centerline) are extra baselines. The fitted predictor
is `fpe fit`'s default (`fpe_jax.fit.DEFAULT_MODEL`, the line model: the car's own line and
speed profile learned from the fit drive).

- Levine: fit on the first 60 % of the lap, report on the last 40 % (targets are the trace itself).
- Simulated: a 60 s fit drive and a separate 40 s test drive (other seed) per track, detection
  latency 0.3 s; the F1TENTH drivers follow the raceline, the predictors get the centerline.

Also the evidence for issue 4's acceptance: per simulated track, fitted FDE / seed-measured-speed
FDE and whether any preset beats the fitted predictor at any step.

Run:  .venv/bin/python experiments/approaches/run.py   (5-7 minutes on the 2-core machine)
Writes experiments/results/approaches.md and experiments/results/approaches_error_vs_horizon.png.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax

from fpe_jax import plots
from fpe_jax.fit._cases import (
    LATENCY_S,
    STUDY_FIT_S,
    STUDY_FIT_SEED,
    STUDY_TEST_S,
    STUDY_TEST_SEED,
    fde_ratio,
    fit_case,
    presets_beating_fitted,
    study_cases,
)
from fpe_jax.fit._fit import DEFAULT_MODEL
from fpe_jax.fit._report import format_fitted
from fpe_jax.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "experiments" / "results"
# the fitted FDE [m] of the blend model this study reported before the line model (issue 13
# asks the line model for <= 0.8x of these on at least 6 of the 7 simulated tracks)
BLEND_FDE_M = {"oval": 0.848, "hairpin": 1.002, "Austin": 0.883, "Catalunya": 0.730}
BLEND_FDE_M |= {"Monza": 0.429, "Silverstone": 0.626, "Spielberg": 0.760}
ORDER = ("fitted", "seed", "seed-measured-speed", "constant-velocity", "linear", "pure-pursuit")
ORDER += ("ctrv", "frenet")
MODEL = DEFAULT_MODEL  # the fitted predictor: what `fpe fit` fits with no flags


def per_step_table(report: dict, dt_s: float) -> str:
    """Markdown: one row per predictor, mean error [m] at every step, then ADE, FDE, miss rate."""
    h = len(report["fitted"]["per_step_m"])
    head = "| predictor | " + " | ".join(f"{dt_s * (k + 1):.1f} s" for k in range(h))
    lines = [head + " | ADE m | FDE m | miss rate |", "|---" * (h + 4) + "|"]
    best = [min(report[n]["per_step_m"][k] for n in report) for k in range(h)]
    for name in ORDER:
        m = report[name]
        cells = [
            f"**{e:.3f}**" if e == best[k] else f"{e:.3f}" for k, e in enumerate(m["per_step_m"])
        ]
        label = plots.APPROACH[name]
        lines.append(
            f"| {label} | "
            + " | ".join(cells)
            + f" | {m['ade_m']:.3f} | {m['fde_m']:.3f} | {m['miss_rate']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    jax.config.update("jax_enable_x64", True)  # fitting and evaluation in float64
    t0, cpu0 = time.perf_counter(), time.process_time()
    results = []
    with Progress() as say:
        say("simulating the drives and reading the Levine lap")
        todo = study_cases(DATA, say)
        for i, case in enumerate(todo):
            say(f"[{i + 1}/{len(todo)}] {case.name}: fitting the {MODEL} model")
            res = fit_case(
                case, model=MODEL, blend="auto", progress=lambda m, n=case.name: say(f"{n}: {m}")
            )
            results.append((case, res))
        say("writing the results")
        RESULTS.mkdir(parents=True, exist_ok=True)
        dt_s = results[0][1].params.settings.dt_s
        fig = plots.error_vs_horizon_figure(
            {
                c.name + (" (real)" if c.latency_s is None else " (sim)"): r.report
                for c, r in results
            },
            dt_s=dt_s,
            names=ORDER,
            title="Mean position error vs horizon on held-out data: thesis approaches 1-4 "
            "vs the fitted predictor",
        )
        png = plots.save(fig, RESULTS / "approaches_error_vs_horizon.png")
        md = RESULTS / "approaches.md"
        wall_cpu_s = (time.perf_counter() - t0, time.process_time() - cpu0)
        md.write_text(markdown(results, dt_s, wall_cpu_s, png.name))
    print(f"wrote {md} and {png}")


def _choice(model: dict) -> str:
    """The chosen model and the inner validation ADEs it was chosen by (if it was chosen)."""
    ade = model["validation_ade_m"]
    if not ade:
        return model["chosen"]
    blend = min((v for k, v in ade.items() if k != "line"), default=float("nan"))
    return f"{model['chosen']} ({ade.get('line', float('nan')):.3f} / {blend:.3f})"


def markdown(results, dt_s: float, wall_cpu_s: tuple[float, float], png: str) -> str:
    lines = [
        "# Thesis approaches 1-4 vs the fitted predictor",
        "",
        "Regenerate: `.venv/bin/python experiments/approaches/run.py` "
        f"(this run: {wall_cpu_s[0] / 60:.1f} min wall, {wall_cpu_s[1] / 60:.1f} min CPU on the "
        "project's shared 2-core machine; mostly XLA compilation, once per track).",
        "",
        "Approach 1 (displacement) = preset `constant-velocity`, 2 = `linear`, 3 = "
        "`pure-pursuit`, 4 = `seed` (the 0.7 blend exactly as the 2019 node ran it, speed "
        "hard-coded to 1 m/s) and `seed-measured-speed` (same rules, measured speed); `ctrv` "
        "(constant turn rate and velocity) and `frenet` (along-track speed held, lateral offset "
        "decaying to the centerline) are extra baselines. The fitted predictor is `fpe fit`'s "
        f"default, `--model {MODEL}`: "
        + (
            "the line model (the car's own line and speed profile learned from the fit drive, a "
            "Frenet rollout on it; where the fit drive never went it keeps the car's own "
            "offset from a prior profile fitted to the track's shape, and its speed ratio)"
            if MODEL == "line"
            else f"the {MODEL} model"
        )
        + ". Errors are on data the fit did not see. Simulated drives: a "
        f"{STUDY_FIT_S:g} s fit drive (seed {STUDY_FIT_SEED}) and a separate {STUDY_TEST_S:g} s "
        f"test drive (seed {STUDY_TEST_SEED}) per track, detection latency {LATENCY_S} s, "
        "targets = the true positions; "
        "on the F1TENTH tracks the driver follows the raceline and the predictors get the "
        "centerline. Miss: final (1.0 s) error > 0.5 m. "
        "On Levine, approaches 1 and 2 coincide: the trace has no yaw, so the heading is the "
        "direction of motion.",
        "",
        f"![error vs horizon]({png})",
        "",
        "## Summary",
        "",
        "Ratio = fitted FDE / `seed-measured-speed` FDE on the test drive (issue 4 asks "
        "<= 0.5 on at least three tracks). vs blend = fitted FDE / the blend model's fitted FDE "
        "this study reported before (issue 13 asks <= 0.8 on at least 6 of 7 simulated tracks). "
        "'Beaten at' lists every preset@step (step 1 = 0.1 s) where a preset's mean error is "
        "below the fitted one.",
        "",
        "| case | fitted ADE m | fitted FDE m | frenet FDE m | seed FDE m | "
        "seed-measured-speed FDE m | ratio | ratio <= 0.5 | blend FDE m | vs blend | beaten at "
        "| fitted delay s (true) | model (line / blend validation ADE m, after auto) | "
        "predictions |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, r in results:
        rep = r.report
        ratio = fde_ratio(rep)
        beaten = presets_beating_fitted(rep)
        real = case.latency_s is None
        true = "real data" if real else f"{case.latency_s:.2f}"
        # the 0.5 ratio is issue 4's criterion for simulated tracks only
        half = "n/a (real)" if real else ("yes" if ratio <= 0.5 else "no")
        old = BLEND_FDE_M.get(case.name)
        vs = f"{old:.3f} | {rep['fitted']['fde_m'] / old:.2f}" if old else "n/a | n/a"
        lines.append(
            f"| {case.name} | {rep['fitted']['ade_m']:.3f} | {rep['fitted']['fde_m']:.3f} | "
            f"{rep['frenet']['fde_m']:.3f} | "
            f"{rep['seed']['fde_m']:.3f} | {rep['seed-measured-speed']['fde_m']:.3f} | "
            f"{ratio:.2f} | {half} | {vs} | "
            f"{', '.join(beaten) if beaten else 'none'} | "
            f"{r.params.physical()['delay_s']:.3f} ({true}) | {_choice(r.info['model'])} | "
            f"{rep['fitted']['n_predictions']} |"
        )
    sims = [(c, r) for c, r in results if c.latency_s is not None]
    n_08 = sum(r.report["fitted"]["fde_m"] <= 0.8 * BLEND_FDE_M[c.name] for c, r in sims)
    n_half = sum(fde_ratio(r.report) <= 0.5 for _, r in sims)
    n_clean = sum(not presets_beating_fitted(r.report) for _, r in sims)
    n_both = sum(
        fde_ratio(r.report) <= 0.5 and not presets_beating_fitted(r.report) for _, r in sims
    )
    lines += [
        "",
        f"Simulated tracks: {n_half} of {len(sims)} have ratio <= 0.5; on {n_clean} of "
        f"{len(sims)} no preset beats the fitted predictor at any step; both hold on {n_both}. "
        f"Fitted FDE <= 0.8x the blend model's on {n_08} of {len(sims)}.",
        "",
    ]
    for case, r in results:
        fitted = format_fitted(r).replace("\n", "; ")
        lines += [
            f"## {case.name}",
            "",
            f"{case.description}. {fitted}.",
            "",
            "Mean error [m] per horizon step (best per column in bold):",
            "",
            per_step_table(r.report, dt_s),
            "",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
