"""The drive-vs-track check's shares on the project's own drives and on wrong waypoints.

Own drives (must pass): simulated drives on the built-in and F1TENTH tracks (noisy detectors and
stops included), the AprilTag test drive, the Levine lap, the full-size bench case. Wrong ones
(must trip): another track, reversed waypoints, waypoints shifted by 50 m. Writes
track_check.md here; thresholds: `fpe_jax.path.MIN_ON_TRACK_SHARE`, `MIN_ALONG_SHARE`.

    .venv/bin/python experiments/hostile/track_check.py     # about 3 minutes
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
DATA = HERE.parents[2] / "shared" / "data"


def main() -> None:
    import run as bench  # experiments/benchmarks/run.py: the full-size case

    from fpe_jax import io, sim
    from fpe_jax.path import (
        MIN_ALONG_SHARE,
        MIN_ON_TRACK_SHARE,
        ON_TRACK_EXTENT,
        ON_TRACK_M,
        build_path,
        track_agreement,
    )

    monza, austin = (str(DATA / f"tracks/{n}_centerline.csv") for n in ("Monza", "Austin"))
    own = {}
    for name in ("oval", "hairpin", "random:1", "random:7", monza, austin):
        r = sim.simulate(name, duration_s=60.0, seed=1)
        own[Path(name).stem] = (r.drive.xy_m, r.centerline_xy_m)
    r = sim.simulate(monza, raceline=str(DATA / "tracks/Monza_raceline.csv"), duration_s=60.0)
    own["Monza raceline"] = (r.drive.xy_m, r.centerline_xy_m)
    noisy = dict(outlier_prob=0.2, sigma_per_m=0.15, rate_hz=40.0)
    for track in ("oval", "hairpin"):
        r = sim.simulate(track, duration_s=60.0, seed=2, sensor=sim.Sensor(**noisy),
                         driver=sim.Driver(stops_per_min=2.0))  # fmt: skip
        own[f"{track}, noisy detector, 2 stops/min"] = (r.drive.xy_m, r.centerline_xy_m)
    r = sim.simulate("hairpin", duration_s=30.0, seed=2, camera=sim.Camera())
    own["AprilTag test drive (hairpin)"] = (r.drive.xy_m, r.centerline_xy_m)
    lev = DATA / "levine"
    levine = (
        np.loadtxt(lev / "actual-poses.csv", delimiter=",")[:, :2],
        np.loadtxt(lev / "levine-waypoints.csv", delimiter=",")[:, :2],
    )
    own["Levine lap (real)"] = levine
    with tempfile.TemporaryDirectory() as tmp:
        bench.fullsize_drive(Path(tmp))
        full = (
            io.load_drive(f"{tmp}/drive.mcap").xy_m,
            io.load_waypoints(f"{tmp}/waypoints.csv").xy_m,
        )
    own["full-size bench case"] = full
    oval, hairpin, mz = own["oval"], own["hairpin"], own["Monza_centerline"]
    wrong = {
        "Monza drive, oval waypoints": (mz[0], oval[1]),
        "oval drive, Monza waypoints": (oval[0], mz[1]),
        "oval drive, hairpin waypoints": (oval[0], hairpin[1]),
        "Austin drive, Monza waypoints": (own["Austin_centerline"][0], mz[1]),
        "oval reversed": (oval[0], oval[1][::-1]),
        "hairpin reversed": (hairpin[0], hairpin[1][::-1]),
        "Levine reversed": (levine[0], levine[1][::-1]),
        "full-size reversed": (full[0], full[1][::-1]),
        "oval shifted 50 m": (oval[0], oval[1] + [50.0, 0.0]),
        "Levine shifted 50 m": (levine[0], levine[1] + [0.0, 50.0]),
        "full-size shifted 50 m": (full[0], full[1] + [50.0, 0.0]),
    }
    lines = [
        "# Drive-vs-track check: shares on own drives and on wrong waypoints",
        "",
        f"`.venv/bin/python experiments/hostile/track_check.py`. near: share of observations "
        f"within `near m` of the waypoints' path, the larger of {ON_TRACK_M:g} m and "
        f"{ON_TRACK_EXTENT:.0%} of the path's extent (must be >= {MIN_ON_TRACK_SHARE:.0%}); "
        f"along: share of the drive's ~2 m moves that start near the path and go its way (must "
        f"be >= {MIN_ALONG_SHARE:.0%}).",
        "",
        "| case | waypoints | near m | near | along | moves | verdict |",
        "| --- | --- | ---: | ---: | ---: | ---: | --- |",
    ]
    for kind, cases in (("own", own), ("wrong", wrong)):
        for name, (xy, wp) in cases.items():
            p = build_path(wp)
            a = track_agreement(xy, p["xy_m"], p["heading_rad"])
            trips = a["share_near"] < MIN_ON_TRACK_SHARE or a["share_along"] < MIN_ALONG_SHARE
            good = trips == (kind == "wrong")
            verdict = ("trips" if trips else "passes") + ("" if good else " (WRONG)")
            lines.append(
                f"| {name} | {kind} | {a['near_m']:.1f} | {a['share_near']:.3f} | "
                f"{a['share_along']:.3f} | {a['n_moves']} | {verdict} |"
            )
            print(lines[-1])
    (HERE / "track_check.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
