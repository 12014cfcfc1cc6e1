"""What a fit reports: the provenance block of a tuned config, the fitted values in two lines and
the Markdown table of held-out metrics (`fpe fit`, `fpe evaluate`, the demo and the studies)."""

from __future__ import annotations

import datetime
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

# the fit's module imports the solvers: the report's readers (`fpe evaluate`) do without it, and
# the hints name it in full so that a run-time checker finds it once a result exists
if TYPE_CHECKING:
    import fpe_jax.fit._fit


def provenance(result: fpe_jax.fit._fit.FitResult, sources: Sequence[str], topics: dict) -> dict:
    """The provenance block of a tuned config."""
    from fpe_jax import __version__  # the package root imports nothing eagerly

    return {
        "drives": list(sources),
        "topics": topics,
        "split": result.info["split"],
        "fit": result.info["fit"],
        "blend_selection_ade_m": result.info["validation_ade_m"],
        "model_selection": result.info["model"],
        "solver": {
            k: result.info[k]
            for k in ("solver", "steps", "presolve_steps", "converged", "loss", "seconds")
        }
        # where a fit ran on several devices or processes (`fpe_jax.fit._processes`)
        | {k: result.info[k] for k in ("devices", "processes") if result.info.get(k, 1) > 1},
        "heldout": result.report,
        "fitted_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "fpe_jax_version": __version__,
    }


def _steps(info: dict) -> str:
    """The solve's steps in words: "27 bfgs steps (+44 on a subsample)"."""
    pre = info["presolve_steps"]
    return f"{info['steps']} {info['solver']} steps" + (f" (+{pre} on a subsample)" if pre else "")


def line_section(result: fpe_jax.fit._fit.FitResult, waypoints: str | None) -> dict | None:
    """The config's `line` section of a line-model fit: the sha256 of the waypoints the line was
    learned on and the file they came from (`waypoints`, None when unknown); None for other
    models."""
    sha = result.info.get("waypoints_sha256")
    return None if sha is None else {"waypoints_sha256": sha, "waypoints": waypoints}


def format_fitted(result: fpe_jax.fit._fit.FitResult) -> str:
    """Two lines: the fitted values, and the per-step weights (or the line); after `--model
    auto` a first line with the validation scores it chose by."""
    p, info = result.params.physical(), result.info
    ade = info.get("model", {}).get("validation_ade_m", {})
    if "line" in ade:  # chosen by --model auto
        blend = min((v for k, v in ade.items() if k != "line"), default=float("nan"))
        choice = f"chosen by --model auto: inner validation ADE line {ade['line']:.3f} m, "
        choice += f"blend {blend:.3f} m\n"
    else:
        choice = ""
    if result.params.settings.model == "line":
        covered = float(np.mean(np.asarray(result.params.line_coverage) > 0))
        return choice + (
            f"fitted (line model, {_steps(info)}): delay "
            f"{p['delay_s']:.3f} s, offset decay {p['offset_tau_s']:.3f} s, speed-profile blend "
            f"{p['speed_tau_s']:.3f} s, pace return {p['pace_return_1ps']:.3f} /s, position "
            f"smoothing {p['position_smoothing']:.2f}"
            + (
                f", filter noise {p['filter_accel_mps2']:.2f} / {p['filter_lat_accel_mps2']:.2f} "
                f"m/s^2, {p['filter_obs_m']:.3f} m, gate {p['filter_gate_sigma']:.2f} sigma\n"
                if result.params.settings.estimator == "kalman"
                else "\n"
            )
            + f"line: {len(p['line_offset_m'])} points, {covered:.0%} "
            f"covered, offset rms {np.sqrt(np.mean(np.square(p['line_offset_m']))):.3f} m"
        )
    return choice + (
        f"fitted ({info['blend']} blend, {_steps(info)}): "
        f"lookahead {p['lookahead_m']:.3f} m + {p['lookahead_gain_s']:.3f} s * v, "
        f"delay {p['delay_s']:.3f} s, speed {p['speed_weight']:.2f} * measured + "
        f"{1 - p['speed_weight']:.2f} * {p['speed_mps']:.2f} m/s\n"
        "weights " + " ".join(f"{w:.3f}" for w in p["weights"])
    )


def md_table(head: str, rows) -> list[str]:
    """The lines of a Markdown table: `head` (its cells joined by " | "), a `|---|` rule, then the
    rows, each a sequence of cells or a string of them joined the same way."""
    rows = [r if isinstance(r, str) else " | ".join(map(str, r)) for r in rows]
    return [f"| {head} |", "|" + "---|" * len(head.split(" | ")), *(f"| {r} |" for r in rows)]


def format_table(report: dict) -> str:
    """A Markdown table of held-out metrics, one row per predictor."""
    h = len(next(iter(report.values()))["per_step_m"])
    steps = [0, h // 2 - 1, h - 1] if h >= 3 else list(range(h))
    head = "predictor | ADE m | FDE m | FDE p90 m | miss rate | "
    head += " | ".join(f"err@{k + 1} m" for k in steps) + " | n"
    rows = [
        [name, *(f"{m[k]:.3f}" for k in ("ade_m", "fde_m", "fde_p90_m", "miss_rate"))]
        + [f"{m['per_step_m'][k]:.3f}" for k in steps]
        + [m["n_predictions"]]
        for name, m in report.items()
    ]
    return "\n".join(md_table(head, rows))
