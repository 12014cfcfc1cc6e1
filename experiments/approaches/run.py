"""The thesis's approaches 1-4 against the fitted predictor, on the real Levine lap and on
simulated drives (built-in oval and hairpin, the five F1TENTH tracks).

Approach 1 (displacement) = the `constant-velocity` preset, 2 = `linear`, 3 = `pure-pursuit`,
4 = `seed` (the 0.7 blend exactly as the 2019 node ran it, speed hard-coded to 1 m/s) and
`seed-measured-speed` (the same rules with the measured speed); `ctrv` is an extra baseline.

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
from fpe_jax.demo import (
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
from fpe_jax.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "experiments" / "results"
# Levine is small (one lap) and real: let the fit choose the blend mode (3 solves). The simulated
# tracks use the position blend (1 solve each) to keep the whole run within a few minutes.
LEVINE_BLEND, SIM_BLEND = "auto", "position"
ORDER = ("fitted", "seed", "seed-measured-speed", "constant-velocity", "linear", "pure-pursuit")
ORDER += ("ctrv",)


def cases(say):
    """(case, blend) pairs: Levine when the shared data is there, then the simulated tracks."""
    return [(c, LEVINE_BLEND if c.latency_s is None else SIM_BLEND) for c in study_cases(DATA, say)]


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
        todo = cases(say)
        for i, (case, blend) in enumerate(todo):
            say(f"[{i + 1}/{len(todo)}] {case.name}: fitting ({blend} blend)")
            res = fit_case(case, blend=blend, progress=lambda m, n=case.name: say(f"{n}: {m}"))
            results.append((case, blend, res))
        say("writing the results")
        RESULTS.mkdir(parents=True, exist_ok=True)
        dt_s = results[0][2].params.settings.dt_s
        fig = plots.error_vs_horizon_figure(
            {
                c.name + (" (real)" if c.latency_s is None else " (sim)"): r.report
                for c, _, r in results
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
        "(constant turn rate and velocity) is an extra baseline. Errors are on data the fit did "
        "not see. Simulated drives: a "
        f"{STUDY_FIT_S:g} s fit drive (seed {STUDY_FIT_SEED}) and a separate {STUDY_TEST_S:g} s "
        f"test drive (seed {STUDY_TEST_SEED}) per track, detection latency {LATENCY_S} s, "
        "targets = the true positions; "
        "on the F1TENTH tracks the driver follows the raceline and the predictors get the "
        f"centerline. Fits: Levine with blend `{LEVINE_BLEND}`, simulated tracks with blend "
        f"`{SIM_BLEND}` (one solve each, for run time). Miss: final (1.0 s) error > 0.5 m. "
        "On Levine, approaches 1 and 2 coincide: the trace has no yaw, so the heading is the "
        "direction of motion.",
        "",
        f"![error vs horizon]({png})",
        "",
        "## Summary (issue 4's acceptance on simulated tracks)",
        "",
        "Ratio = fitted FDE / `seed-measured-speed` FDE on the test drive (the acceptance asks "
        "<= 0.5 on at least three tracks). 'Beaten at' lists every preset@step (step 1 = 0.1 s) "
        "where a preset's mean error is below the fitted one.",
        "",
        "| case | fitted ADE m | fitted FDE m | seed FDE m | seed-measured-speed FDE m | ratio "
        "| ratio <= 0.5 | beaten at | fitted delay s (true) | predictions |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, _, r in results:
        rep = r.report
        ratio = fde_ratio(rep)
        beaten = presets_beating_fitted(rep)
        real = case.latency_s is None
        true = "real data" if real else f"{case.latency_s:.2f}"
        # the 0.5 ratio is issue 4's criterion for simulated tracks only
        half = "n/a (real)" if real else ("yes" if ratio <= 0.5 else "no")
        lines.append(
            f"| {case.name} | {rep['fitted']['ade_m']:.3f} | {rep['fitted']['fde_m']:.3f} | "
            f"{rep['seed']['fde_m']:.3f} | {rep['seed-measured-speed']['fde_m']:.3f} | "
            f"{ratio:.2f} | {half} | "
            f"{', '.join(beaten) if beaten else 'none'} | "
            f"{r.params.physical()['delay_s']:.3f} ({true}) | {rep['fitted']['n_predictions']} |"
        )
    sims = [(c, r) for c, _, r in results if c.latency_s is not None]
    n_half = sum(fde_ratio(r.report) <= 0.5 for _, r in sims)
    n_clean = sum(not presets_beating_fitted(r.report) for _, r in sims)
    n_both = sum(
        fde_ratio(r.report) <= 0.5 and not presets_beating_fitted(r.report) for _, r in sims
    )
    lines += [
        "",
        f"Simulated tracks: {n_half} of {len(sims)} have ratio <= 0.5; on {n_clean} of "
        f"{len(sims)} no preset beats the fitted predictor at any step; both hold on {n_both}.",
        "",
    ]
    for case, blend, r in results:
        p = r.params.physical()
        lines += [
            f"## {case.name}",
            "",
            f"{case.description}. Fitted ({r.info['blend']} blend"
            + (", chosen on an inner validation split" if blend == "auto" else "")
            + f", {r.info['steps']} solver steps): lookahead {p['lookahead_m']:.3f} m + "
            f"{p['lookahead_gain_s']:.3f} s * v, delay {p['delay_s']:.3f} s, speed "
            f"{p['speed_weight']:.2f} * measured + {1 - p['speed_weight']:.2f} * "
            f"{p['speed_mps']:.2f} m/s; weights "
            + " ".join(f"{w:.3f}" for w in p["weights"])
            + ".",
            "",
            "Mean error [m] per horizon step (best per column in bold):",
            "",
            per_step_table(r.report, dt_s),
            "",
        ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
