"""Draw what a Foxglove recording of `fpe view` holds at one moment, top-down, with matplotlib.

Foxglove Studio cannot run here (its app needs the network), so this is the project's stand-in
for a screenshot: it runs `fpe view --out` on the sample drive (data/samples/drive.mcap, the
config fit/sim-oval.json, the oval's waypoints), reads the MCAP back, decodes each message
with protobuf from the schema stored in the file, and draws the scene entities that are alive
at the chosen time (the latest entity of each id per topic, within its lifetime): the track's
line, the observed car (sphere and heading arrow), the predicted line and the 1-sigma ellipses.
Primitives are drawn as Foxglove's 3D panel would show them from above: lines as lines, flat
ellipsoids as ellipses, arrows as arrows, in each primitive's colour.

    .venv/bin/python experiments/foxglove/render.py            # -> docs/images/foxglove_scene.png
    .venv/bin/python experiments/foxglove/render.py --at 17.5 --out /tmp/x.png
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Ellipse, FancyArrow, Patch  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from fpe_jax.io import scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
FPE = str(Path(sys.executable).with_name("fpe"))


def message_class(name: str, descriptor_set: bytes):
    """The protobuf class `name` from a schema's serialized FileDescriptorSet."""
    pool = descriptor_pool.DescriptorPool()
    files = list(descriptor_pb2.FileDescriptorSet.FromString(descriptor_set).file)
    done: set[str] = set()
    while files:  # dependencies first
        ready = [f for f in files if set(f.dependency) <= done]
        for f in ready:
            pool.Add(f)
            done.add(f.name)
        files = [f for f in files if f.name not in done]
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def alive_entities(path: Path, at_ns: int) -> list:
    """The SceneEntity messages shown at `at_ns` [ns]: per (topic, id), the latest one logged
    at or before it whose lifetime (0: forever) has not run out."""
    latest: dict[tuple[str, str], tuple[int, object]] = {}
    classes: dict[int, type] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(ending_at=at_ns):
            if schema.name != "foxglove.SceneUpdate":
                continue
            if schema.id not in classes:
                classes[schema.id] = message_class(schema.name, schema.data)
            for e in classes[schema.id].FromString(message.data).entities:
                latest[(channel.topic, e.id)] = (message.log_time, e)
    alive = []
    for ns, e in latest.values():
        life = e.lifetime.seconds * 10**9 + e.lifetime.nanos
        if life == 0 or ns + life >= at_ns:
            alive.append(e)
    return alive


def _yaw(q) -> float:
    return float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))


def _rgba(c) -> tuple:
    return (c.r, c.g, c.b, c.a)


def draw(ax, entities) -> None:
    """Lines, spheres (as ellipses) and arrows of the entities, seen from above."""
    for e in entities:
        for line in e.lines:
            xy = np.array([[p.x, p.y] for p in line.points])
            ax.plot(*xy.T, color=_rgba(line.color), lw=2.0 if e.id != "centre_line" else 1.5)
        for s in e.spheres:
            p = s.pose.position
            ax.add_patch(
                Ellipse(
                    (p.x, p.y),
                    s.size.x,
                    s.size.y,
                    angle=np.degrees(_yaw(s.pose.orientation)),
                    facecolor=_rgba(s.color),
                    edgecolor=(*_rgba(s.color)[:3], min(1.0, 2 * s.color.a)),
                    lw=0.8,
                )
            )
        for a in e.arrows:
            p, yaw = a.pose.position, _yaw(a.pose.orientation)
            length = a.shaft_length + a.head_length
            ax.add_patch(
                FancyArrow(
                    p.x,
                    p.y,
                    length * np.cos(yaw),
                    length * np.sin(yaw),
                    width=a.shaft_diameter,
                    head_width=a.head_diameter,
                    head_length=a.head_length,
                    length_includes_head=True,
                    color=_rgba(a.color),
                )
            )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", type=float, default=13.0, help="log time [s] to draw (13.0)")
    ap.add_argument("--out", default=str(REPO / "docs" / "images" / "foxglove_scene.png"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "scene.mcap"
        cmd = [
            FPE,
            "view",
            str(REPO / "data" / "samples" / "drive.mcap"),
            "--config",
            str(REPO / "fit" / "sim-oval.json"),
            "--waypoints",
            str(REPO / "data" / "tracks" / "oval.csv"),
            "--out",
            str(rec),
            "--quiet",
        ]
        subprocess.run(cmd, check=True)
        at_ns = round(args.at * 1e9)
        entities = alive_entities(rec, at_ns)

    fig, (ax, zoom) = plt.subplots(1, 2, figsize=(12, 4.6), width_ratios=(1.75, 1))
    for a in (ax, zoom):
        a.set_facecolor((0.12, 0.12, 0.14))  # the 3D panel's dark background
        draw(a, entities)
        a.set_aspect("equal")
        a.set_xlabel("x [m] (map)")
    ax.set_ylabel("y [m] (map)")
    ax.autoscale_view()
    car = next(e for e in entities if e.arrows).spheres[0].pose.position
    path = np.array(
        [[p.x, p.y] for e in entities if e.spheres and not e.arrows for p in e.lines[0].points]
    )
    mid = (np.array([car.x, car.y]) + path[-1]) / 2
    zoom.set_xlim(mid[0] - 3.5, mid[0] + 3.5)
    zoom.set_ylim(mid[1] - 3.5, mid[1] + 3.5)
    ax.set_title(f"fpe view: the recorded scene at t = {args.at:.1f} s, seen from above")
    zoom.set_title("around the car")
    handles = [
        Line2D([], [], color=scene.TRACK_RGBA, label="/track: centre line"),
        Line2D([], [], color=scene.OBSERVATION_RGBA, marker="o", ls="", label="/observations"),
        Line2D([], [], color=scene.PREDICTION_RGBA, label="predicted path (1 s)"),
        Patch(color=scene.ELLIPSE_RGBA, label="1-sigma ellipse per step"),
    ]
    zoom.legend(handles=handles, loc="lower left", fontsize=8, framealpha=0.9)
    fig.text(
        0.5,
        0.01,
        "Drawn by matplotlib from the MCAP that `fpe view --out` writes (the same messages "
        "its Foxglove WebSocket server sends); not a Foxglove Studio screenshot.",
        ha="center",
        fontsize=8,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out} ({len(entities)} entities at t = {args.at} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
