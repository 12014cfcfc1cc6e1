"""Speed shift: a config fitted on slow laps, tested on fast laps of the same track.

Per track: fit drives at speed factor 0.45 (the driver's target speeds x 0.45) of the same
duration as the fast one (60 s: less of the track covered) and of the same distance (60 x 0.85 /
0.45 s), a fit drive at 0.85, and a separate test drive at 0.85 (other seed); all with 0.3 s
detection latency. Each fit drive gives a line-model config (`fpe fit`'s default), scored on the
test drive with the `frenet` preset. Ratio = FDE(fit at 0.45) / FDE(fit at 0.85) (issue 13 asks
<= 1.15 on at least three tracks, and the slow fit below `frenet`).

Run:  .venv/bin/python experiments/speed_shift/run.py   (about 3 minutes on the 2-core machine)
Writes experiments/results/speed_shift.md.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax

ROOT = Path(__file__).resolve().parents[2]
TRACKS_DIR = ROOT.parent / "shared" / "data" / "tracks"
RESULTS = ROOT / "experiments" / "results"
SLOW, FAST = 0.45, 0.85
FIT_S, TEST_S = 60.0, 40.0


def drives(track: str, fit_s: float = FIT_S, test_s: float = TEST_S):
    """(centerline, slow fit drive (fit_s), slow fit drive over the fast one's distance, fast fit
    drive, fast test drive) on one track."""
    from fpe_jax.sim._sim import Driver, simulate

    kw = {}
    if track not in ("oval", "hairpin"):
        kw["raceline"] = TRACKS_DIR / f"{track}_raceline.csv"
        track = TRACKS_DIR / f"{track}_centerline.csv"

    def sim(factor, seed, duration):
        driver = dataclasses.replace(Driver(), speed_factor=factor)
        return simulate(track, duration_s=duration, seed=seed, driver=driver, **kw)

    slow = sim(SLOW, 1, fit_s)
    far = sim(SLOW, 1, fit_s * FAST / SLOW).drive
    return (
        slow.centerline_xy_m,
        slow.drive,
        far,
        sim(FAST, 1, fit_s).drive,
        sim(FAST, 2, test_s).drive,
    )


def speed_shift(track: str, **kw) -> dict:
    """FDE [m] on the fast test drive of the configs fitted slow and fast, and of `frenet`."""
    from fpe_jax.fit._fit import fit
    from fpe_jax.geometry._track import Track

    wp, slow, far, fast, test = drives(track, **kw)
    trk = Track.from_waypoints(wp)
    out = {}
    for name, drv in (("slow", slow), ("far", far), ("fast", fast)):
        res = fit([drv], [trk], test_drives=[test], test_tracks=[trk])
        out[name] = res.report["fitted"]["fde_m"]
        out["frenet"] = res.report["frenet"]["fde_m"]
        out["seed-measured-speed"] = res.report["seed-measured-speed"]["fde_m"]
        out[f"{name}_params"] = res.params.physical()
    out["ratio"] = out["slow"] / out["fast"]
    out["ratio_far"] = out["far"] / out["fast"]
    # the blend model's default fit has no memorised speed either: the same shift for it
    for name, drv in (("slow", slow), ("fast", fast)):
        res = fit([drv], [trk], test_drives=[test], test_tracks=[trk], model="blend")
        out[f"blend_{name}"] = res.report["fitted"]["fde_m"]
        out[f"blend_{name}_speed_weight"] = res.params.physical()["speed_weight"]
    out["blend_ratio"] = out["blend_slow"] / out["blend_fast"]
    return out


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    tracks = ["oval", "hairpin"]
    if TRACKS_DIR.is_dir():
        tracks += ["Austin", "Monza", "Silverstone"]
    rows = []
    for track in tracks:
        print(f"{track} ...", flush=True)
        rows.append((track, speed_shift(track)))
    lines = [
        "# Speed shift: fitted on slow laps, tested on fast laps",
        "",
        f"Regenerate: `.venv/bin/python experiments/speed_shift/run.py` (this run: "
        f"{(time.perf_counter() - t0) / 60:.1f} min on the shared 2-core machine).",
        "",
        f"Per track: line-model configs (`fpe fit`'s default) fitted on a {FIT_S:g} s drive at "
        f"speed factor {FAST} (fast fit), on a {FIT_S:g} s drive at {SLOW} (slow fit, {FIT_S:g} "
        f"s: it covers less of the track; there the line model keeps the car's own offset from "
        f"a prior profile fitted to the track's shape and follows its speed ratio) and on a "
        f"drive at {SLOW} over the fast one's distance ({FIT_S * FAST / SLOW:.0f} s), all scored "
        f"on a separate {TEST_S:g} s test drive at {FAST} (seed 2); latency 0.3 s. Ratio = "
        "FDE(slow fit) / FDE(fast fit); the acceptance asks <= 1.15 on at least three tracks, "
        "and the slow fit below `frenet`.",
        "",
        f"| track | FDE fast fit m | FDE slow fit, {FIT_S:g} s m | ratio | FDE slow fit, same "
        "distance m | ratio | frenet FDE m | slow fits < frenet | seed-measured-speed FDE m |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for track, r in rows:
        below = r["slow"] < r["frenet"] and r["far"] < r["frenet"]
        lines.append(
            f"| {track} | {r['fast']:.3f} | {r['slow']:.3f} | {r['ratio']:.2f} | "
            f"{r['far']:.3f} | {r['ratio_far']:.2f} | {r['frenet']:.3f} | "
            f"{'yes' if below else 'no'} | {r['seed-measured-speed']:.3f} |"
        )
    n = sum(r["ratio"] <= 1.15 for _, r in rows)
    n_far = sum(r["ratio_far"] <= 1.15 for _, r in rows)
    lines += [
        "",
        f"Ratio <= 1.15 on {n} of {len(rows)} tracks with the {FIT_S:g} s slow drive, on "
        f"{n_far} of {len(rows)} with the slow drive over the same distance.",
        "",
        f"The blend model (`--model blend`, default groups: no `speed`, so it drives at the "
        f"measured speed) fitted on the same {FIT_S:g} s slow and fast drives:",
        "",
        "| track | blend FDE fast fit m | blend FDE slow fit m | ratio | speed_weight (slow, "
        "fast) |",
        "|---|---|---|---|---|",
    ]
    for track, r in rows:
        lines.append(
            f"| {track} | {r['blend_fast']:.3f} | {r['blend_slow']:.3f} | "
            f"{r['blend_ratio']:.2f} | {r['blend_slow_speed_weight']:.2f}, "
            f"{r['blend_fast_speed_weight']:.2f} |"
        )
    lines.append("")
    for track, r in rows:
        for name in ("slow", "far", "fast"):
            p = r[f"{name}_params"]
            lines.append(
                f"- {track}, {name} fit: delay {p['delay_s']:.3f} s, offset decay "
                f"{p['offset_tau_s']:.3f} s, profile blend {p['speed_tau_s']:.3f} s"
            )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "speed_shift.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {RESULTS / 'speed_shift.md'}")


if __name__ == "__main__":
    main()
