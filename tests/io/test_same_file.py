"""An output path that names one of the command's inputs is refused, --force or not, whatever the
spelling (relative, symlink, hard link), and the input is left as it was."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from fpe_jax import io
from fpe_jax.cli import main
from fpe_jax.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"


def _inputs(tmp_path: Path) -> dict[str, Path]:
    """Copies of a drive, its waypoints, cars and a config in tmp_path."""
    files = dict(
        drive=DATA / "samples" / "drive.csv",
        waypoints=DATA / "tracks" / "oval.csv",
        cars=DATA / "samples" / "cars.csv",
        config=Path(__file__).resolve().parents[2] / "fit" / "sim-oval.json",
    )
    out = {}
    for name, src in files.items():
        out[name] = tmp_path / src.name
        shutil.copyfile(src, out[name])
    return out


def _spellings(tmp_path: Path, target: Path) -> list[str]:
    """Other names of `target`: relative with ./, a symlink, a hard link."""
    link = tmp_path / f"link-{target.name}"
    link.symlink_to(target)
    hard = tmp_path / f"hard-{target.name}"
    os.link(target, hard)
    rel = os.path.relpath(target, Path.cwd())
    return [str(target), "./" + rel if not rel.startswith("..") else rel, str(link), str(hard)]


def _refused(argv: list, capsys, *inputs: Path) -> None:
    before = {p: p.read_bytes() for p in inputs}
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "same file as the input" in err, err
    assert "Traceback" not in err
    for p, data in before.items():
        assert p.read_bytes() == data, f"{p} was changed"


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_predict_convert_batch_refuse_an_input_as_out(tmp_path, capsys, force):
    f = _inputs(tmp_path)
    wp, drive = f["waypoints"], f["drive"]
    for out in _spellings(tmp_path, drive):
        _refused(
            ["predict", drive, "--waypoints", wp, "--preset", "linear", "--out", out, *force],
            capsys,
            drive,
        )
        _refused(["convert", drive, "--out", out, *force], capsys, drive)
    for out in _spellings(tmp_path, wp)[1:]:
        _refused(
            ["predict", drive, "--waypoints", wp, "--preset", "linear", "--out", out, *force],
            capsys,
            wp,
        )
    cars = f["cars"]
    for out in _spellings(tmp_path, cars):
        _refused(
            ["batch", cars, "--waypoints", wp, "--preset", "linear", "--out", out, *force],
            capsys,
            cars,
        )


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_fit_refuses_the_waypoints_or_a_drive_as_out(tmp_path, capsys, force):
    f = _inputs(tmp_path)
    wp, drive = f["waypoints"], f["drive"]
    for target in (wp, drive):
        for out in _spellings(tmp_path, target)[:2]:
            argv = ["fit", drive, "--waypoints", wp, "--out", out, *force]
            _refused(argv, capsys, wp, drive)


def test_fit_refuses_a_recipe_waypoints_file_as_its_out(tmp_path, capsys):
    f = _inputs(tmp_path)
    recipe = tmp_path / "r.toml"
    recipe.write_text(
        f'out = "{f["waypoints"]}"\nwaypoints = "{f["waypoints"]}"\n'
        f'[[drives]]\npath = "{f["drive"]}"\n'
    )
    _refused(["fit", recipe, "--force"], capsys, f["waypoints"], f["drive"])


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_export_refuses_its_config_or_waypoints_as_out(tmp_path, capsys, force):
    """Every format, every spelling; the StableHLO artifact's sidecar (OUT.json) and a
    `--format all` folder that holds the config as its config.json count as well."""
    f = _inputs(tmp_path)
    cfg, wp = f["config"], f["waypoints"]
    for out in _spellings(tmp_path, cfg):
        for fmt in ("json", "ros2"):
            _refused(["export", cfg, "--format", fmt, "--out", out, *force], capsys, cfg)
    argv = ["export", cfg, "--format", "ros2", "--waypoints", wp, "--out", wp, *force]
    _refused(argv, capsys, wp, cfg)
    stem = cfg.with_suffix("")  # the artifact's sidecar would be the config itself
    argv = ["export", cfg, "--format", "stablehlo", "--waypoints", wp, "--out", stem, *force]
    _refused(argv, capsys, cfg)
    car = tmp_path / "car"
    car.mkdir()
    shutil.copyfile(cfg, car / "config.json")  # a re-export of car/config.json into car/
    argv = ["export", car / "config.json", "--format", "all", "--waypoints", wp, "--out", car]
    _refused([*argv, *force], capsys, car / "config.json")


def test_simulate_refuses_to_replace_its_track_file(tmp_path, capsys):
    folder = tmp_path / "sim"
    folder.mkdir()
    track = folder / "waypoints.csv"  # the name simulate writes its centre line to
    shutil.copyfile(DATA / "tracks" / "oval.csv", track)
    argv = ["simulate", "--track", track, "--duration", "5", "--out", folder, "--force"]
    _refused(argv, capsys, track)
    link = tmp_path / "elsewhere.csv"
    link.symlink_to(track)
    argv = ["simulate", "--track", link, "--duration", "5", "--out", folder, "--force"]
    _refused(argv, capsys, track)


def test_check_not_input_library(tmp_path):
    a = tmp_path / "a.csv"
    a.write_text("x\n")
    io.check_not_input(tmp_path / "new.csv", [a])  # nothing there yet: fine
    io.check_not_input(a, [None, tmp_path / "missing.csv"])
    other = tmp_path / "b.csv"
    other.write_text("x\n")
    io.check_not_input(other, [a])  # equal content, different file: fine
    with pytest.raises(InputError, match="same file as the input"):
        io.check_output_path(tmp_path / "." / "a.csv", True, inputs=[a])


def test_recipes_show_a_refit_that_leaves_the_committed_configs_alone():
    """Each recipe's comment shows a command writing under out/, and says that without --out it
    writes (and with --force regenerates) the committed config beside it."""
    recipes = sorted((ROOT / "fit").glob("*.toml"))
    assert recipes
    for recipe in recipes:
        comments = [line for line in recipe.read_text().splitlines() if line.startswith("#")]
        text = "\n".join(comments)
        rel = recipe.relative_to(ROOT)
        assert f"fpe fit {rel} --out out/{recipe.stem}.json" in text, rel
        commands = [c for c in comments if "fpe fit" in c]
        assert all("--out out/" in c for c in commands), commands
        assert "regenerates that file" in text and f"fit/{recipe.stem}.json" in text


def test_documented_commands_leave_the_committed_files_alone():
    """The `fpe` commands in the shell blocks of README.md and docs/*.md write under out/ or to
    files of the user's: none names (by --out, or a recipe's `out` without one) a file that git
    tracks, unless its own comment says it regenerates a committed file."""
    import re
    import shlex
    import subprocess
    import tomllib

    git = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if git.returncode != 0:
        pytest.skip(f"not a git checkout: {git.stderr.strip()}")
    tracked = set(git.stdout.splitlines())
    commands, writes_tracked = 0, []
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for block in re.findall(r"```(?:bash|sh|shell|console)?\n(.*?)```", doc.read_text(), re.S):
            for line in block.replace("\\\n", " ").splitlines():
                cmd, _, comment = line.partition(" #")
                if not cmd.strip().startswith("fpe "):
                    continue
                commands += 1
                argv = shlex.split(cmd)
                target = argv[argv.index("--out") + 1] if "--out" in argv else None
                if target is None and argv[1] == "fit" and argv[2].endswith(".toml"):
                    recipe = ROOT / argv[2]
                    out = tomllib.loads(recipe.read_text()).get("out")
                    target = None if out is None else str((recipe.parent / out).relative_to(ROOT))
                if target is None:
                    continue
                target = os.path.normpath(target)
                if (target in tracked or any(f.startswith(target + "/") for f in tracked)) and (
                    "regenerat" not in comment
                ):
                    writes_tracked.append(f"{doc.name}: {cmd.strip()}")
    assert commands > 20
    assert writes_tracked == []


def test_a_recipe_simulating_a_track_file_reads_it_beside_the_recipe(tmp_path, capsys, monkeypatch):
    """A recipe's `simulate.track` file is relative to the recipe's folder, as its other paths
    are (whatever the working folder), and is one of its inputs: `out` naming it is refused."""
    from fpe_jax.fit._recipe import load_recipe

    folder = tmp_path / "recipe"
    folder.mkdir()
    track = folder / "trk.csv"
    shutil.copyfile(DATA / "tracks" / "oval.csv", track)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "trk.csv").write_text("x,y\n0,0\n1,0\n1,1\n")  # not the recipe's track
    monkeypatch.chdir(elsewhere)
    sim = '[[drives]]\nsimulate = { track = "trk.csv", duration_s = 5 }\n'
    (folder / "ok.toml").write_text('out = "c.json"\n' + sim)
    recipe = load_recipe(folder / "ok.toml")
    assert track in recipe.inputs
    np.testing.assert_allclose(recipe.drives[0][1], io.load_waypoints(track).xy_m, atol=1e-9)
    (folder / "r.toml").write_text('out = "trk.csv"\n' + sim)
    _refused(["fit", folder / "r.toml", "--force", "--quiet"], capsys, track)
