"""What the fit learns: per-step blend weights against the thesis's 0.7^i, the lookahead, and the
delay offset against the true detection latency over a sweep 0 ... 0.5 s.

- Latency sweep: on the built-in oval, for each latency a 40 s fit drive (seed 1) and a separate
  20 s test drive (seed 2), both with that latency; position blend (one solve per fit).
- Real data: the Levine lap (fit on the first 60 %, blend chosen by the fit) for its weights and
  lookahead; its true delay is unknown.

Run:  .venv/bin/python experiments/weights/run.py   (about 3 minutes on the 2-core machine)
Writes experiments/results/weights.md and experiments/results/weights.png.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import matplotlib.pyplot as plt
import numpy as np

from fpe_jax import plots
from fpe_jax.fit._cases import DELAY_TOLERANCE_S, fde_ratio, fit_case, real_cases, simulated_case
from fpe_jax.fit._report import md_table
from fpe_jax.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "experiments" / "results"
LATENCIES_S = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
TRACK, FIT_S, TEST_S, FIT_SEED, TEST_SEED = "oval", 40.0, 20.0, 1, 2


def lookahead_at(p: dict, v_mps: float) -> float:
    """The fitted pure-pursuit lookahead [m] at speed v [m/s]."""
    return p["lookahead_m"] + p["lookahead_gain_s"] * v_mps


def median_speed(drive) -> float:
    """Median speed [m/s] of a drive: from its truth when it has one, else from observations."""
    if drive.has_truth:
        return float(np.median(drive.truth_v_mps))
    new = np.r_[True, np.any(drive.xy_m[1:] != drive.xy_m[:-1], axis=1)]
    t, xy = drive.t_s[new], drive.xy_m[new]
    v = np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.diff(t)
    return float(np.median(v))


def figure(sweep, levine, levine_v, dt_s: float, png: Path) -> None:
    """Weights (left), fitted delay vs latency (middle), fitted lookahead (right).

    sweep: (latency [s], FitResult, median speed [m/s]) per latency; levine: FitResult or None.
    """
    fig, (ax_w, ax_d, ax_l) = plt.subplots(1, 3, figsize=(20, 6), width_ratios=[1.3, 1, 1])
    h = len(sweep[0][1].params.physical()["weights"])
    lat = np.array([x for x, _, _ in sweep])
    t = dt_s * np.arange(1, h + 1)
    ax_w.plot(
        t, 0.7 ** np.arange(h), "s--", color="tab:red", lw=2, label="seed: 0.7^i (heading blend)"
    )
    cmap = plt.get_cmap("viridis")
    curves = [
        (f"{TRACK}, latency {a:.1f} s", r, "o-", cmap(j / max(len(sweep) - 1, 1)), 4)
        for j, (a, r, _) in enumerate(sweep)
    ] + ([("Levine, real", levine, "D-", "black", 5)] if levine is not None else [])
    for label, r, style, c, ms in curves:
        w = r.params.physical()["weights"]
        ax_w.plot(t, w, style, color=c, ms=ms, label=f"{label} ({r.info['blend']} blend)")
    ax_w.set_ylim(-0.03, 1.03)
    ax_w.set_xlabel("horizon [s]")
    ax_w.set_ylabel("weight on the linear rollout [-] (1 = linear, 0 = pure pursuit)")
    ax_w.set_title("Per-step blend weights: fitted vs the thesis's 0.7^i", fontsize=11)
    ax_w.grid(alpha=0.3)
    ax_w.legend(fontsize=8, loc="upper right")

    delay = np.array([r.params.physical()["delay_s"] for _, r, _ in sweep])
    band = lat - DELAY_TOLERANCE_S, lat + DELAY_TOLERANCE_S
    ax_d.fill_between(lat, *band, color="0.85", label=f"true +- {DELAY_TOLERANCE_S} s")
    ax_d.plot(lat, lat, "--", color="0.3", label="fitted = true")
    ax_d.plot(lat, delay, "o-", color="tab:green", ms=7, label="fitted delay offset (oval)")
    ax_d.set_xlabel("true detection latency [s]")
    ax_d.set_ylabel("fitted delay offset [s]")
    ax_d.set_title("Fitted delay vs the simulated latency", fontsize=11)
    ax_d.set_aspect("equal", adjustable="datalim")
    ax_d.grid(alpha=0.3)
    ax_d.legend(fontsize=9, loc="upper left")

    look = [lookahead_at(r.params.physical(), v) for _, r, v in sweep]
    ax_l.axhline(2.0, color="tab:red", ls="--", lw=2, label="seed: 2.0 m")
    label = f"fitted, {TRACK} (at its median speed {sweep[0][2]:.1f} m/s)"
    ax_l.plot(lat, look, "o-", color="tab:green", ms=7, label=label)
    if levine is not None:
        label = f"fitted, Levine (at its median speed {levine_v:.2f} m/s)"
        at_v = lookahead_at(levine.params.physical(), levine_v)
        ax_l.axhline(at_v, color="black", lw=1.5, label=label)
    ax_l.set_ylim(0, max(max(look), 2.0) * 1.25)
    ax_l.set_xlabel("true detection latency [s]")
    ax_l.set_ylabel("pure-pursuit lookahead L0 + gain * v [m]")
    ax_l.set_title("Fitted lookahead", fontsize=11)
    ax_l.grid(alpha=0.3)
    ax_l.legend(fontsize=9, loc="lower right")
    fig.suptitle(
        f"What the fit learns ({TRACK}: {FIT_S:g} s fit drive per latency; Levine: first 60 % "
        "of the real lap)"
    )
    fig.tight_layout()
    plots.save(fig, png)


def main() -> None:
    jax.config.update("jax_enable_x64", True)  # fitting and evaluation in float64
    t0 = time.perf_counter()
    sweep, levine, levine_v = [], None, None
    with Progress() as say:
        kw = dict(fit_s=FIT_S, test_s=TEST_S, fit_seed=FIT_SEED, test_seed=TEST_SEED)
        for lat in LATENCIES_S:
            case = simulated_case(TRACK, latency_s=lat, **kw)
            say(f"{TRACK}, latency {lat:.1f} s: fitting")
            progress = lambda m, a=lat: say(f"{a:.1f} s: {m}")  # noqa: E731
            r = fit_case(case, model="blend", blend="position", progress=progress)
            sweep.append((lat, r, median_speed(case.fit_drive)))
        for case in real_cases(DATA, say):
            say("Levine: fitting (auto blend)")
            levine = fit_case(
                case, model="blend", blend="auto", progress=lambda m: say(f"Levine: {m}")
            )
            levine_v = median_speed(case.fit_drive)
        say("writing the results")
        dt_s = sweep[0][1].params.settings.dt_s
        png = RESULTS / "weights.png"
        figure(sweep, levine, levine_v, dt_s, png)
        md = RESULTS / "weights.md"
        md.write_text(markdown(sweep, levine, levine_v, time.perf_counter() - t0))
    print(f"wrote {md} and {png}")


def markdown(sweep, levine, levine_v, seconds: float) -> str:
    n_ok = sum(abs(r.params.physical()["delay_s"] - a) <= DELAY_TOLERANCE_S for a, r, _ in sweep)
    rows = [(f"{TRACK}, latency {a:.1f} s", r) for a, r, _ in sweep]
    rows += [(f"Levine ({levine.info['blend']} blend)", levine)] if levine is not None else []
    delays = []
    for lat, r, v in sweep:
        p = r.params.physical()
        err = p["delay_s"] - lat
        delays.append(
            f"{lat:.1f} | {p['delay_s']:.3f} | {err:+.3f} | "
            f"{'yes' if abs(err) <= DELAY_TOLERANCE_S else 'no'} | "
            f"{p['lookahead_m']:.3f} + {p['lookahead_gain_s']:.3f} v | {lookahead_at(p, v):.2f} | "
            f"{v:.2f} | {r.report['fitted']['fde_m']:.3f} | {fde_ratio(r.report):.2f}"
        )
    lines = [
        "# What the fit learns: weights, lookahead, delay",
        "",
        "Regenerate: `.venv/bin/python experiments/weights/run.py` (this run: "
        f"{seconds / 60:.1f} min).",
        "",
        f"Latency sweep on the built-in {TRACK}: per latency a {FIT_S:g} s fit drive (seed "
        f"{FIT_SEED}) and a separate {TEST_S:g} s test drive (seed {TEST_SEED}), position blend. "
        "Levine: the real lap, fit on the first 60 % (blend chosen by the fit). Weights are the "
        "weight on the linear rollout at 0.1 s ... 1.0 s (1 = linear, 0 = pure pursuit). The "
        "seed's 0.7^i (1.0 at 0.1 s, as the 2019 code ran it) blends *headings* step by step; "
        "the fitted position blend mixes the two rollouts' *positions*, so the numbers are not "
        "the same quantity, but both say how far to trust the current heading vs the track.",
        "",
        "![weights](weights.png)",
        "",
        "## Delay offset vs true latency",
        "",
        *md_table(
            f"true latency s | fitted delay s | error s | within {DELAY_TOLERANCE_S} s | lookahead "
            "m + gain s * v | lookahead at median speed m | median speed m/s | held-out FDE m | "
            "FDE / seed-measured-speed FDE",
            delays,
        ),
        "",
        f"{n_ok} of {len(sweep)} latencies recovered within {DELAY_TOLERANCE_S} s.",
        "",
        "## Per-step weights",
        "",
        *md_table(
            "fit | " + " | ".join(f"{0.1 * (k + 1):.1f} s" for k in range(10)),
            [["seed 0.7^i", *(f"{0.7**k:.3f}" for k in range(10))]]
            + [[label, *(f"{x:.3f}" for x in r.params.physical()["weights"])] for label, r in rows],
        ),
    ]
    if levine is not None:
        p = levine.params.physical()
        lines += [
            "",
            f"Levine: lookahead {p['lookahead_m']:.3f} m + {p['lookahead_gain_s']:.3f} s * v "
            f"= {lookahead_at(p, levine_v):.2f} m at its median observed speed {levine_v:.2f} m/s "
            f"(the seed: 2.0 m); delay offset {p['delay_s']:.3f} s; speed "
            f"{p['speed_weight']:.2f} * measured + {1 - p['speed_weight']:.2f} * "
            f"{p['speed_mps']:.2f} m/s.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
