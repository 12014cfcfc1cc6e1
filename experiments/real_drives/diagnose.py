"""Why a real drive's fit misses: what the fitted values are, whether the car's motion in the
held-out part differs from the fit part, and whether the fitted ellipses are calibrated where
they were fitted (the fit part's cross-fitted residuals) as well as on the held-out part.

The same drives, detector, split and fit as experiments/real_drives/run.py (its functions).
Per drive it reports:
- the fitted delay, time constants, position smoothing and filter values;
- the skid-pad circle fitted (least squares) to the recorded positions of the fit part and of
  the held-out part: how far its centre moved, its radius, and the median angle between the
  car's yaw and its direction of motion (a slide shows as an angle that grows with speed);
- coverage of the fitted ellipses (1 / 2 sigma) and the rms residual along and across the
  track at 1 s and 3 s, on the fit part's cross-fitted predictions (each from a line learned on
  the rest of the fit part, as the ellipses were fitted) and on the held-out part;
- median FDE at 1 s and 3 s of the fitted predictor and the Frenet baseline on the held-out
  targets due by the end of the run's steady part and on those due after it;
- median FDE at 1 s and 3 s with the speed time constant replaced by longer ones (nothing
  refitted), on the fit part's cross-fitted predictions and on the held-out part.

Run:  .venv/bin/python experiments/real_drives/diagnose.py [--mirror DIR] [--seed N]
Writes experiments/results/real_drives_diagnosis.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SPEED_TAUS_S = (1.0, 3.0, 10.0)


def _study():
    spec = importlib.util.spec_from_file_location("real_drives_run", HERE / "run.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses resolve their annotations through it
    spec.loader.exec_module(mod)
    return mod


def circle(xy_m: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (2,) [m] and radius [m] of the least-squares circle through points (N, 2)."""
    x, y = xy_m[:, 0], xy_m[:, 1]
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    d, e, f = np.linalg.lstsq(a, -(x * x + y * y), rcond=None)[0]
    c = np.array([-d / 2, -e / 2])
    return c, float(np.sqrt(c @ c - f))


def slip_deg(t_s: np.ndarray, xy_m: np.ndarray, yaw_rad: np.ndarray) -> float:
    """Median angle [deg] from the yaw to the direction of motion."""
    v = np.gradient(xy_m, t_s, axis=0)
    motion = np.arctan2(v[:, 1], v[:, 0])
    return float(np.degrees(np.median(np.angle(np.exp(1j * (motion - yaw_rad))))))


def calibration(params, uncertainty, ds, xy_m) -> dict:
    """Coverage (1, 2 sigma) over steps 1-H and rms residuals (along, cross) [m] at 1 s, 3 s."""
    from fpe_jax.evaluate._evaluate import _track_residuals, prediction_covariance
    from fpe_jax.evaluate._metrics import coverage

    res = _track_residuals(xy_m, ds, params)
    cov = prediction_covariance(params, ds.states(params), ds.track, uncertainty)
    m = ds.targets.mask
    out = coverage(res, m, cov)
    for k in (10, 30):
        out[f"rms_{k}"] = np.sqrt(np.mean(res[m[:, k - 1], k - 1] ** 2, axis=0))
    return out


def fde(ds, xy_m) -> tuple[float, float]:
    """Median final error [m] at 1 s and 3 s."""
    e = np.linalg.norm(xy_m - ds.targets.xy_m, axis=-1)
    m = ds.targets.mask
    return tuple(float(np.median(e[m[:, k - 1], k - 1])) for k in (10, 30))


def split_fde(ds, xy_m, t_end_s: float) -> list[tuple[int, float, int, float]]:
    """At 1 s and 3 s: (count, median final error [m]) of the targets due by t_end_s, and of
    those due after it."""
    due = ds.drive.t_s[ds.targets.rows]
    e = np.linalg.norm(xy_m - ds.targets.xy_m, axis=-1)
    out = []
    for k in (10, 30):
        m = ds.targets.mask[:, k - 1]
        before, after = m & (due + 0.1 * k <= t_end_s), m & (due + 0.1 * k > t_end_s)
        med = [float(np.median(e[r, k - 1])) if r.any() else float("nan") for r in (before, after)]
        out.append((int(before.sum()), med[0], int(after.sum()), med[1]))
    return out


def diagnose(study, src, poses, seed: int) -> dict:
    import jax.numpy as jnp

    from fpe_jax.evaluate._evaluate import _cross_fitted, make_datasets, predict_targets
    from fpe_jax.fit._fit import baseline, fit
    from fpe_jax.model._params import presets, with_settings

    case = study.make_case(src, poses, seed)
    track = case.track()
    init = with_settings(presets["default"], horizon=study.HORIZON)
    res = fit(
        [case.fit_drive], [track], init=init, test_drives=[case.test_drive], test_tracks=[track]
    )
    p = res.params
    fit_ds, test_ds = (
        make_datasets([d], [track], p.settings, what, kalman=True)[0]
        for d, what in ((case.fit_drive, "training"), (case.test_drive, "held-out"))
    )
    t = poses["t_s"]
    fit_rows = t <= t[0] + (1 - study.HOLDOUT) * (t[-1] - t[0])
    (c_fit, r_fit), (c_test, r_test) = (circle(poses["xy_m"][m]) for m in (fit_rows, ~fit_rows))
    out = dict(
        values={k: float(getattr(p, k)) for k in VALUES},
        centre_shift_m=float(np.linalg.norm(c_test - c_fit)),
        radius_m=(r_fit, r_test),
        slip_deg=tuple(
            slip_deg(t[m], poses["xy_m"][m], poses["yaw_rad"][m]) for m in (fit_rows, ~fit_rows)
        ),
        cal_fit=calibration(p, res.uncertainty, fit_ds, _cross_fitted(p, fit_ds)),
        cal_test=calibration(p, res.uncertainty, test_ds, predict_targets(p, test_ds).xy_m),
        taus={},
        steady_end_s=float(study.steady_part(poses)["t_s"][-1]),
    )
    out["by_end"] = {
        name: split_fde(test_ds, predict_targets(q, test_ds).xy_m, out["steady_end_s"])
        for name, q in (("fitted", p), ("frenet", baseline("frenet", p.settings)))
    }
    for tau in (None, *SPEED_TAUS_S):
        q = p if tau is None else dataclasses.replace(p, speed_tau_s=jnp.asarray(tau))
        out["taus"][tau] = (
            fde(fit_ds, _cross_fitted(q, fit_ds)),
            fde(test_ds, predict_targets(q, test_ds).xy_m),
        )
    return out


VALUES = ("delay_s", "offset_tau_s", "speed_tau_s", "position_smoothing", "filter_obs_m")


def markdown(rows, wall_s: float) -> str:
    lines = [
        "# Real drives: why a fit misses",
        "",
        "Regenerate: `.venv/bin/python experiments/real_drives/diagnose.py` "
        f"(this run: {wall_s / 60:.1f} min wall on the shared 2-core machine). The drives, "
        "detector, split and fit of `experiments/real_drives/run.py`.",
        "",
        "## Fitted values and the car's motion",
        "",
        "Circle: least squares through the recorded positions of the fit part and of the "
        "held-out part. Slip: median angle from yaw to the direction of motion.",
        "",
        "| drive | " + " | ".join(VALUES) + " | centre moved fit->held-out m | radius fit / "
        "held-out m | slip fit / held-out deg |",
        "|---" * (len(VALUES) + 4) + "|",
    ]
    for src, r in rows:
        vals = " | ".join(f"{r['values'][k]:.3f}" for k in VALUES)
        lines.append(
            f"| {src.name} | {vals} | {r['centre_shift_m']:.3f} | "
            f"{r['radius_m'][0]:.3f} / {r['radius_m'][1]:.3f} | "
            f"{r['slip_deg'][0]:.1f} / {r['slip_deg'][1]:.1f} |"
        )
    lines += [
        "",
        "## Calibration where the ellipses were fitted and where they are scored",
        "",
        "Fit part: its cross-fitted predictions (each from a line learned on the rest of the fit "
        "part, the residuals the ellipses are fitted on). Coverage over steps 1-30 (ideal "
        "39.3 % / 86.5 %); rms residual along / across the track [m].",
        "",
        "| drive | part | 1 sigma | 2 sigma | rms at 1 s | rms at 3 s |",
        "|---|---|---|---|---|---|",
    ]
    for src, r in rows:
        for part, key in (("fit (cross-fitted)", "cal_fit"), ("held-out", "cal_test")):
            c = r[key]
            lines.append(
                f"| {src.name} | {part} | {c['coverage_1sigma']:.0%} | {c['coverage_2sigma']:.0%}"
                f" | {c['rms_10'][0]:.3f} / {c['rms_10'][1]:.3f} | "
                f"{c['rms_30'][0]:.3f} / {c['rms_30'][1]:.3f} |"
            )
    lines += [
        "",
        "## Before and after the run's end",
        "",
        "The held-out targets due by the end of the run's steady part (`run.steady_part`: the "
        "last time the car covers 80 % of its median speed over 0.5 s) and those due after it "
        "(the car leaving its circle and stopping): count and median final error [m].",
        "",
        "| drive | steady until s | predictor | 1 s: by the end | 1 s: after | 3 s: by the end "
        "| 3 s: after |",
        "|---|---|---|---|---|---|---|",
    ]
    for src, r in rows:
        for name, parts in r["by_end"].items():
            cells = " | ".join(f"{a:.3f} (n={na}) | {b:.3f} (n={nb})" for na, a, nb, b in parts)
            lines.append(f"| {src.name} | {r['steady_end_s']:.2f} | {name} | {cells} |")
    lines += [
        "",
        "## The speed time constant",
        "",
        "Median FDE at 1 s / 3 s [m] with `speed_tau_s` replaced (nothing refitted): on the fit "
        "part's cross-fitted predictions, and on the held-out part.",
        "",
        "| drive | speed_tau_s | fit part (cross-fitted) | held-out |",
        "|---|---|---|---|",
    ]
    for src, r in rows:
        for tau, (f, h) in r["taus"].items():
            name = f"{r['values']['speed_tau_s']:.3f} (fitted)" if tau is None else f"{tau:g}"
            lines.append(
                f"| {src.name} | {name} | {f[0]:.3f} / {f[1]:.3f} | {h[0]:.3f} / {h[1]:.3f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    study = _study()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    study.add_source_args(ap)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    # the diagnosis is of the skid-pad circles (the circle through each part's positions)
    for src in (s for s in study.selected(args) if s.track == "circle"):
        try:
            poses, _ = study.load_source(args.mirror, src)
        except FileNotFoundError as e:
            print(f"left out {src.name}: {e}")
            continue
        print(f"{src.name}: fitting", flush=True)
        rows.append((src, diagnose(study, src, poses, args.seed)))
    if not rows:
        print("no source present: nothing written")
        return 0
    out = study.RESULTS / f"real_drives_diagnosis{study.partial(args)}.md"
    out.write_text(markdown(rows, time.perf_counter() - t0))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
