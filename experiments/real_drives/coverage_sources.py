"""Where the long-horizon fit's ellipses miss on the real drives' held-out parts, and what the
adapting runner's online calibration measures there.

The same drives, detector, split and long-horizon fit (`--fit delay,tau,pace,smoothing,filter`)
as experiments/real_drives/run.py (its functions, and calibration.py's replay of the runner's
calibration). Per drive it reports:
- the fit's own per-prediction ellipses on the fit part's cross-fitted predictions (where they
  were fitted) and on the held-out part: coverage, the ellipses' median standard deviation at
  1 s along and across the track, and the median absolute residual there; the held-out
  coverage by phase (predictions made in the part's first COLD_S, in its last END_S, the rest);
- the fitted config through the adapting runner with its online calibration
  (`AdaptiveRunner(calibrate=True)`), started at the held-out part (as run.py runs it) and at the
  start of the recording (a runner tracking the car since it was first seen; the fit part's
  detections first, scored on the same held-out targets): median FDE at 1 s and 3 s, its ratio
  to the best baseline there, and the coverage;
- what the calibration measures errors against: the runner's filtered estimate of where the
  car was (a detection stamped t shows the car at t - delay), against the recorded pose then;
- the calibration replayed on the same stream with that reference replaced by the recorded pose
  (a diagnostic only: no runner has it), under the runner's mean rule and under a rule that
  keeps each step's median squared Mahalanobis distance at the Gaussian's (2 ln 2; one log
  scale per step moved by GAIN x (1[d2 > 2 ln 2] - 1/2) x 2 per realised error, on top of the
  mean rule's per-axis scales); and the per drive, step and axis scales chosen in hindsight on
  the held-out errors (calibration.py's `hindsight_cov`, the median).

Run:  .venv/bin/python experiments/real_drives/coverage_sources.py [--mirror DIR] [--seed N]
Writes experiments/results/real_drives_coverage_sources.md.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from calibration import (  # calibration.py (this script's folder is on the path)
    COLD_S,
    END_S,
    LocalLevel,
    MeanRule,
    d2,
    hindsight_cov,
    hit,
    record_stream,
    replay,
    whole_recording,
)
from diagnose import _study

FREE = ("delay", "tau", "pace", "smoothing", "filter")
GAIN = 0.1
SMOOTH_N = 9  # detections in the smoothed reference's lines (about 0.8 s)
SCALE_FLOOR = 1e-3
MEDIAN_D2 = 2 * math.log(2)  # the median of a 2-D standard Gaussian's squared distance


class MedianRule(MeanRule):
    """The mean rule's per-axis scales times one log scale per step that keeps the step's
    median d2 at MEDIAN_D2 (a stochastic approximation of the median)."""

    def __init__(self, *a):
        super().__init__(*a)
        self.log_c = np.zeros(self.horizon)

    def learn(self, k, r, tag):
        q = float(r @ np.linalg.inv(self.covariance()[k]) @ r)
        self.log_c[k] += GAIN * 2 * ((q > MEDIAN_D2) - 0.5)
        super().learn(k, r, tag)

    def scale_now(self):
        return self.scale * np.exp(self.log_c)[:, None]


def fit_long(study, case):
    """The long-horizon fit of the case (3 s horizon), as `run.py --fit ...` fits it."""
    from fpe_jax.fit._fit import fit
    from fpe_jax.model._params import presets, with_settings

    track = case.track()
    init = with_settings(presets["default"], horizon=study.HORIZON)
    return fit(
        [case.fit_drive],
        [track],
        init=init,
        test_drives=[case.test_drive],
        test_tracks=[track],
        free=FREE,
    )


def static_ellipses(case, res) -> dict:
    """The fit's per-prediction ellipses on the fit part's cross-fitted predictions and on the
    held-out part: per part d2 (N, H), mask, residuals (N, H, 2), covariances, and the
    prediction times from the part's start (N,)."""
    from fpe_jax.evaluate._evaluate import (
        _cross_fitted,
        _track_residuals,
        make_datasets,
        predict_targets,
        prediction_covariance,
    )

    p, track = res.params, case.track()
    out = {}
    for part, drive, what in (("fit", case.fit_drive, "training"), ("held-out", case.test_drive,
                                                                       "held-out")):  # fmt: skip
        ds = make_datasets([drive], [track], p.settings, what, kalman=True)[0]
        xy = _cross_fitted(p, ds) if part == "fit" else predict_targets(p, ds).xy_m
        r = _track_residuals(xy, ds, p)
        cov = prediction_covariance(p, ds.states(p), track, res.uncertainty)
        out[part] = dict(
            res=r,
            cov=cov,
            q=d2(r, cov),
            mask=ds.targets.mask,
            age=drive.t_s[ds.targets.rows] - drive.t_s[0],
            due=drive.t_s[ds.targets.rows][:, None]
            + p.settings.dt_s * np.arange(1, p.settings.horizon + 1),
            duration=float(drive.t_s[-1] - drive.t_s[0]),
        )
    return out


def baselines_fde(case, res) -> dict:
    """Median FDE [m] at 1 s and 3 s of every baseline on the held-out part: {label: {name: m}}."""
    from fpe_jax.evaluate._evaluate import heldout_predictions
    from fpe_jax.fit._fit import BASELINES, baseline

    s = res.params.settings
    held = heldout_predictions(
        case.test_drive, case.track(), {n: baseline(n, s) for n in BASELINES}
    )
    out = {}
    for label, k in (("1 s", 10), ("3 s", 30)):
        ok = held.mask[:, k - 1]
        out[label] = {
            n: float(np.median(np.linalg.norm(p[ok, k - 1] - held.target_xy_m[ok, k - 1], axis=1)))
            for n, p in held.pred_xy_m.items()
        }
    return out


def stream_fde(d: dict) -> dict:
    """Median FDE [m] at 1 s and 3 s of a recorded runner stream (its residuals' norms)."""
    e = np.linalg.norm(d["res"], axis=-1)
    steps = (("1 s", 10), ("3 s", 30))
    return {lab: float(np.median(e[d["mask"][:, k - 1], k - 1])) for lab, k in steps}


def true_reference(d: dict, drive, poses: dict, case) -> tuple[dict, np.ndarray]:
    """The stream d with each filtered observation the calibration was given replaced by the
    recorded pose at (its stamp - the config's delay), and the (along, cross) error [m] of the
    runner's own reference against that pose, for the observations of the held-out part."""
    from fpe_jax.drive import local_frame

    _, _, _, origin = local_frame(drive, case.waypoints_xy_m)
    t0, held_t0 = drive.t_s[0], case.test_drive.t_s[0]
    events, err = [], []
    for e in d["events"]:
        if e[1] == "o":
            t = e[2] + t0 - d["delay"]
            x, y = (np.interp(t, poses["t_s"], poses["xy_m"][:, i]) - origin[i] for i in (0, 1))
            if e[2] + t0 >= held_t0:
                # the path's direction of motion at the recorded pose: the ellipses' frame
                tt = np.array([t - 0.02, t + 0.02])
                v = [np.diff(np.interp(tt, poses["t_s"], poses["xy_m"][:, i]))[0] for i in (0, 1)]
                h = math.atan2(v[1], v[0])
                dx, dy = e[3] - x, e[4] - y
                err.append(
                    (math.cos(h) * dx + math.sin(h) * dy, -math.sin(h) * dx + math.cos(h) * dy)
                )
            e = (e[0], "o", e[2], x, y)
        events.append(e)
    return dict(d, events=events), np.asarray(err)


class SmoothedMean(MeanRule):
    """The mean rule on observation events that carry their reference's variance (per axis) as
    a sixth field (`smoothed_reference`), which it leaves aside."""

    subtract = False

    def observe(self, t, x, y, var=(0.0, 0.0)):
        self.ref_var = np.asarray(var) if self.subtract else np.zeros(2)
        super().observe(t, x, y)


class DeconvolvedMean(SmoothedMean):
    """The mean rule on r^2 minus the reference's own variance (per axis), its scales kept at
    least SCALE_FLOOR."""

    subtract = True

    def z(self, k, r, tag):
        return (r * r - self.ref_var) / self.var[k]

    def refresh(self):
        super().refresh()
        self.scale = np.maximum(self.scale, SCALE_FLOOR)


def _line_at_centre(t_s: np.ndarray, y: np.ndarray, t_c: float) -> tuple[float, float]:
    """A least-squares line through (t_s, y) with the points beyond 3 robust sigmas left out
    (twice), evaluated at t_c: (value, its variance from the kept points' scatter)."""
    keep = np.ones(len(t_s), bool)
    for _ in range(2):
        a = np.stack([np.ones(keep.sum()), t_s[keep] - t_c], 1)
        coef = np.linalg.lstsq(a, y[keep], rcond=None)[0]
        r = y - coef[0] - coef[1] * (t_s - t_c)
        keep = np.abs(r) <= 3 * (1.4826 * np.median(np.abs(r[keep])) + 1e-9)
    n, tk = int(keep.sum()), t_s[keep] - t_c
    leverage = 1.0 / n + tk.mean() ** 2 / max(float(np.sum((tk - tk.mean()) ** 2)), 1e-12)
    return float(coef[0]), float(np.sum(r[keep] ** 2) / max(n - 2, 1) * leverage)


def smoothed_reference(d: dict, drive, case) -> dict:
    """The stream d with each filtered observation the calibration was given replaced by a
    smoothed one: at the newest SMOOTH_N detections, lines in time through their arc length
    and offset along the waypoints' path, evaluated at the middle detection's stamp, that
    stamp and the lines' variances there carried with it (`DeconvolvedMean`)."""
    from fpe_jax.drive import local_frame
    from fpe_jax.node._core import frenet_to_map
    from fpe_jax.runner._runner import RunnerPath

    local, wp, _, _ = local_frame(drive, case.waypoints_xy_m)
    path = RunnerPath(wp)
    s_m, d_m = np.empty(len(local.t_s)), np.empty(len(local.t_s))
    s_prev = None
    for i, (x, y) in enumerate(local.xy_m.tolist()):
        s = path.project(x, y)
        s = s if s_prev is None else path.continuous(s, s_prev)  # counts laps
        h = path.heading_at(s)
        px, py = path.point_at(s)
        s_m[i], d_m[i] = s, math.cos(h) * (y - py) - math.sin(h) * (x - px)  # left of travel
        s_prev = s
    events = []
    for e in d["events"]:
        if e[1] != "o":
            events.append(e)
            continue
        k = e[0]
        if k + 1 < SMOOTH_N:
            continue
        rows = np.arange(k + 1 - SMOOTH_N, k + 1)
        t_c = float(local.t_s[rows[SMOOTH_N // 2]])
        (s_c, var_s), (d_c, var_d) = (_line_at_centre(local.t_s[rows], y[rows], t_c)
                                      for y in (s_m, d_m))  # fmt: skip
        events.append((k, "o", t_c, *frenet_to_map(path, s_c, d_c), (var_s, var_d)))
    return dict(d, events=events)


def local_level(d: dict) -> np.ndarray:
    """(M,) calibration.py's local level (the recent realised short-step errors against their
    scale) as it stood when each scored prediction was made, replayed on stream d."""
    return replay(d, LocalLevel, read=lambda rule: rule.level)


def study_drive(study, src, poses, seed: int, edges=()) -> dict:
    case = study.make_case(src, poses, seed, edges)
    res = fit_long(study, case)
    whole = whole_recording(study, poses, case, seed)
    cold = record_stream(case, res)
    warm = record_stream(case, res, whole)
    oracle, ref_err = true_reference(warm, whole[0], poses, case)
    return dict(
        halt_s=float(study.steady_part(poses)["t_s"][-1]),
        smoothed=smoothed_reference(warm, whole[0], case),
        static=static_ellipses(case, res),
        baselines=baselines_fde(case, res),
        cold=cold,
        warm=warm,
        oracle=oracle,
        ref_err=ref_err,
    )


def _pct(v: float) -> str:
    return f"{100 * v:.1f} %"


def _pooled(qs) -> str:
    c1, c2 = hit(np.concatenate(qs))
    per = ", ".join("{:.0f}/{:.0f}".format(*(100 * np.array(hit(q)))) for q in qs)
    return f"{_pct(c1)} | {_pct(c2)} | {per}"


def markdown(names, rows, wall_s: float, steady: bool = False) -> str:
    lines = [
        "# Real drives: where the long-horizon fit's ellipses miss",
        "",
        "Regenerate: `.venv/bin/python experiments/real_drives/coverage_sources.py"
        + (" --steady" if steady else "")
        + f"` (this run: {wall_s / 60:.1f} min wall on the shared 2-core machine)."
        + (
            " Each recording cut to its steady part (run.py's `steady_part`: its run-up and "
            "final halt left out)."
            if steady
            else ""
        )
        + " The drives, detector, split "
        "and long-horizon fit (`--fit delay,tau,pace,smoothing,filter`) of "
        "`experiments/real_drives/run.py`; scored on the held-out last 40 % against the recorded "
        "poses, steps 1-30 pooled. Ideal coverage: 39.3 % at 1 sigma, 86.5 % at 2 sigma.",
        "",
        "## The fit's own ellipses",
        "",
        "Median ellipse standard deviation and median absolute residual at 1 s (step 10), "
        "along / across the track [m], on the fit part's cross-fitted predictions (where the "
        "ellipses were fitted) and on the held-out part.",
        "",
        "| drive | coverage fit part | coverage held-out | ellipse sd, fit part ; held-out | "
        "median abs residual fit | median abs residual held-out |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in zip(names, rows):
        cells = [name]
        for part in ("fit", "held-out"):
            s = r["static"][part]
            cells.append("{:.0f} / {:.0f} %".format(*(100 * np.array(hit(s["q"][s["mask"]])))))
        sd = []
        for part in ("fit", "held-out"):
            s = r["static"][part]
            ok = s["mask"][:, 9]
            c = s["cov"][ok, 9]
            sd.append(
                f"{np.sqrt(np.median(c[:, 0, 0])):.3f} / {np.sqrt(np.median(c[:, 1, 1])):.3f}"
            )
        cells.append(" ; ".join(sd))
        for part in ("fit", "held-out"):
            s = r["static"][part]
            a = np.median(np.abs(s["res"][s["mask"][:, 9], 9]), axis=0)
            cells.append(f"{a[0]:.3f} / {a[1]:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Held-out coverage by phase (predictions made in the part's first {COLD_S} s, in its "
        f"last {END_S} s, the rest), pooled:",
        "",
        "| phase | share of targets | 1 sigma | 2 sigma |",
        "|---|---|---|---|",
    ]
    phases = {"first 0.6 s": [], "middle": [], "last 1.5 s": []}
    for r in rows:
        s = r["static"]["held-out"]
        m, q = s["mask"], s["q"]
        cold = (s["age"] < COLD_S)[:, None] & m
        end = (s["age"] > s["duration"] - END_S)[:, None] & m & ~cold
        phases["first 0.6 s"].append(q[cold])
        phases["last 1.5 s"].append(q[end])
        phases["middle"].append(q[m & ~cold & ~end])
    total = sum(len(np.concatenate(v)) for v in phases.values())
    for label, qs in phases.items():
        q = np.concatenate(qs)
        c1, c2 = hit(q)
        lines.append(f"| {label} | {_pct(len(q) / total)} | {_pct(c1)} | {_pct(c2)} |")
    lines += [
        "",
        "## The adapting runner, started at the held-out part or at the recording's start",
        "",
        "Median FDE [m] and its ratio to the best baseline on the drive; coverage of the "
        "runner's calibrated ellipses (the mean rule, `AdaptiveRunner(calibrate=True)`).",
        "",
        "| drive | start | FDE 1 s | ratio | FDE 3 s | ratio | 1 / 2 sigma |",
        "|---|---|---|---|---|---|---|",
    ]
    ratios = {k: {"1 s": [], "3 s": []} for k in ("cold", "warm")}
    for name, r in zip(names, rows):
        for key, label in (("cold", "held-out part"), ("warm", "recording")):
            f = stream_fde(r[key])
            cells = [name, label]
            for lab in ("1 s", "3 s"):
                best = min(r["baselines"][lab].values())
                ratios[key][lab].append(f[lab] / best)
                cells += [f"{f[lab]:.3f}", f"{f[lab] / best:.2f}"]
            d = r[key]
            cells.append(
                "{:.0f} / {:.0f} %".format(
                    *(100 * np.array(hit(d2(d["res"], d["cov"])[d["mask"]])))
                )
            )
            lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for key, label in (("cold", "held-out part"), ("warm", "recording")):
        qs = [d2(r[key]["res"], r[key]["cov"])[r[key]["mask"]] for r in rows]
        c1, c2 = hit(np.concatenate(qs))
        rr = ratios[key]
        lost = sum(max(a, b) >= 1 for a, b in zip(rr["1 s"], rr["3 s"]))
        lines.append(
            f"Started at the {label}: median ratio {np.median(rr['1 s']):.2f} at 1 s, "
            f"{np.median(rr['3 s']):.2f} at 3 s, drives lost to a baseline {lost} of "
            f"{len(rows)}; pooled coverage {_pct(c1)} / {_pct(c2)}."
        )
        lines.append("")
    lines += [
        "## What the calibration measures errors against",
        "",
        "The runner's filtered estimate of where the car was (the reference each realised "
        "error is taken against) minus the recorded pose then, over the held-out part's "
        "observations, along / across the track [m], beside the true error of the runner's "
        "step-1 predictions (started at the recording).",
        "",
        "| drive | reference rms | reference median abs | prediction step 1 rms | "
        "prediction step 1 median abs |",
        "|---|---|---|---|---|",
    ]
    for name, r in zip(names, rows):
        e = r["ref_err"]
        d = r["warm"]
        p = d["res"][d["mask"][:, 0], 0]
        rms = lambda a: (
            f"{np.sqrt(np.mean(a[:, 0] ** 2)):.3f} / {np.sqrt(np.mean(a[:, 1] ** 2)):.3f}"
        )  # noqa: E731
        med = lambda a: "{:.3f} / {:.3f}".format(*np.median(np.abs(a), axis=0))  # noqa: E731
        lines.append(f"| {name} | {rms(e)} | {med(e)} | {rms(p)} | {med(p)} |")
    lines += [
        "",
        "## The calibration replayed with other references and rules",
        "",
        "The runner started at the recording; each rule replayed on its recorded stream "
        "(calibration.py's replay), every held-out prediction scored with the ellipses the rule "
        "gave it. 'Recorded pose' replaces the filtered reference by the recorded pose at the "
        "same time: a diagnostic, no runner has it. 'Median rule': the mean rule's per-axis "
        f"scales times one log scale per step keeping the median d2 at 2 ln 2 (gain {GAIN}).",
        "",
        "| reference | rule | 1 sigma | 2 sigma | per drive (" + ", ".join(names) + ") |",
        "|---|---|---|---|---|",
    ]
    for ref, key in (("filtered (the runner's)", "warm"), ("recorded pose", "oracle")):
        for rule, cls in (("mean (the runner's)", MeanRule), ("median rule", MedianRule)):
            qs = [d2(r[key]["res"], replay(r[key], cls))[r[key]["mask"]] for r in rows]
            lines.append(f"| {ref} | {rule} | {_pooled(qs)} |")
    for rule, cls in (("mean (the runner's)", SmoothedMean), ("mean of r^2 - reference variance",
                                                           DeconvolvedMean)):  # fmt: skip
        qs = [d2(r["warm"]["res"], replay(r["smoothed"], cls))[r["warm"]["mask"]] for r in rows]
        lines.append(f"| smoothed ({SMOOTH_N} detections) | {rule} | {_pooled(qs)} |")
    qs = [d2(r["warm"]["res"], hindsight_cov(r["warm"], "median"))[r["warm"]["mask"]] for r in rows]
    lines.append(
        f"| none: chosen in hindsight | median of z / 0.455 per drive, step, axis | {_pooled(qs)} |"
    )
    lines += [
        "",
        "## What a per-prediction factor could lean on",
        "",
        "Correlation of ln d2 (under the hindsight scales above, so the drive's and the step's "
        "level left out) with what the runner knows when it predicts: its speed deviation from "
        "its learned profile |ln(v / v(s))|, the recent level of its realised short-step errors "
        "(calibration.py's local level) and the time into the held-out part (whose end is the "
        "halt below); at steps 1, 10 and 30.",
        "",
        "| drive | speed deviation | recent error level (ln) | time into the held-out part |",
        "|---|---|---|---|",
    ]
    for name, r in zip(names, rows):
        d = r["warm"]
        q = d2(d["res"], hindsight_cov(d, "median"))
        feats = (d["speed_dev"][d["rows"]], np.log(local_level(d)), d["age"])
        cells = []
        for f in feats:
            cs = []
            for h in (0, 9, 29):
                ok = d["mask"][:, h]
                cs.append(f"{np.corrcoef(np.log(q[ok, h] + 1e-12), f[ok])[0, 1]:+.2f}")
            cells.append(" / ".join(cs))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if steady:  # the halt is already left out
        return "\n".join(lines) + "\n"
    lines += [
        "",
        "## The recordings' final halt",
        "",
        "The skid-pad recordings end with the car halting within a few tenths of a second "
        "after the last time its speed over 0.5 s is at least 80 % of its median (run.py's "
        "`steady_part`); the full-size ones (cut where their speed first falls below 5 m/s) "
        "with the car slowing down (LVMS) or at speed (Putnam). The held-out targets due after "
        "that time, and their coverage under the fit's own ellipses, the runner's (started at "
        "the recording) and the hindsight scales above:",
        "",
        "| drive | halt from [s] | share of targets | fit's ellipses | runner's | hindsight |",
        "|---|---|---|---|---|---|",
    ]
    after, before = [[], [], []], [[], [], []]
    for name, r in zip(names, rows):
        s = r["static"]["held-out"]
        m = s["mask"]
        late = (s["due"] > r["halt_s"]) & m
        qs = (s["q"], d2(r["warm"]["res"], r["warm"]["cov"]),
              d2(r["warm"]["res"], hindsight_cov(r["warm"], "median")))  # fmt: skip
        cells = []
        for i, q in enumerate(qs):
            after[i].append(q[late])
            before[i].append(q[m & ~late])
            cells.append("{:.0f} / {:.0f} %".format(*(100 * np.array(hit(q[late])))))
        lines.append(
            f"| {name} | {r['halt_s']:.2f} | {_pct(late.sum() / m.sum())} | "
            + " | ".join(cells)
            + " |"
        )
    lines.append("")
    lines.append(
        "Pooled without those targets: the fit's ellipses "
        + ", the runner's ".join(
            "{:.1f} / {:.1f} %".format(*(100 * np.array(hit(np.concatenate(b)))))
            for b in before[:2]
        )
        + ", the hindsight scales {:.1f} / {:.1f} %.".format(
            *(100 * np.array(hit(np.concatenate(before[2]))))
        )
    )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    study = _study()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    study.add_source_args(ap)
    ap.add_argument(
        "--steady",
        action="store_true",
        help="only each recording's steady part (run.py's `steady_part`); the results then go "
        "to real_drives_coverage_sources_steady.md",
    )
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    names, rows = [], []
    for src in study.selected(args):
        try:
            poses, edges = study.load_source(args.mirror, src)
        except FileNotFoundError as e:
            print(f"left out {src.name}: {e}")
            continue
        if args.steady:
            poses = study.steady_part(poses)
        print(f"{src.name}: fitting", flush=True)
        names.append(src.name.replace("F1TENTH skid-pad ", ""))
        rows.append(study_drive(study, src, poses, args.seed, edges))
    if not rows:
        print("no source present: nothing written")
        return 0
    stem = f"real_drives_coverage_sources{'_steady' if args.steady else ''}{study.partial(args)}"
    out = study.RESULTS / f"{stem}.md"
    out.write_text(markdown(names, rows, time.perf_counter() - t0, args.steady))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
