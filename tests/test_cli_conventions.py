"""What every command's help and output promise (issue 19): an example in each command's help that parses
with the command's own options, no raw placeholders in any help text, ``--quiet`` on every command that
logs, progress bars on the long stages (frames rendered, characterize-sensor, the results file)."""

from __future__ import annotations

import re
import shlex

import pytest
import typer
from typer.testing import CliRunner

from needlecli.cli.app import app

#: commands that print a report and never log: no --quiet to give them
REPORTS = {"list", "explain", "log info", "kernels status"}


def _commands():
    root = typer.main.get_command(app)

    def walk(c, path):
        yield " ".join(path), c
        for name, sub in sorted((getattr(c, "commands", None) or {}).items()):
            yield from walk(sub, [*path, name])

    return list(walk(root, []))


COMMANDS = _commands()
LEAVES = [(p, c) for p, c in COMMANDS if not getattr(c, "commands", None)]


def test_every_command_is_walked():
    names = {p for p, _ in LEAVES}
    assert {"simulate", "evaluate", "validate", "explain", "fit-em", "crossval", "sweep", "compare",
            "characterize-sensor", "log import-csv", "log info", "import ultrasteer"} <= names, names


@pytest.mark.parametrize("path, cmd", COMMANDS, ids=[p or "needle" for p, _ in COMMANDS])
def test_help_has_an_example_and_no_raw_placeholders(path, cmd):
    r = CliRunner().invoke(app, [*path.split(), "-h"], terminal_width=200)
    assert r.exit_code == 0, r.output
    text = r.output
    raw = re.findall(r"<[a-z][a-z0-9_\[\], ]*>|\{[a-z_]+\}|\[default: *\]", text)
    assert not raw, f"needle {path} --help shows raw placeholders {raw}"
    assert "Example: needle " + (path.split()[0] if path else "") in text, text


@pytest.mark.parametrize("path, cmd", LEAVES, ids=[p for p, _ in LEAVES])
def test_the_example_parses_with_the_commands_own_options(path, cmd):
    doc = cmd.help or ""
    lines = [ln for ln in doc.splitlines() if ln.strip().startswith("Example: ")]
    assert len(lines) == 1, doc
    argv = shlex.split(lines[0].strip()[len("Example: "):])
    assert argv[: 1 + len(path.split())] == ["needle", *path.split()], argv
    args = argv[1 + len(path.split()):]
    ctx = cmd.make_context(path, list(args))  # unknown options, missing arguments, bad types raise here
    assert ctx.params


@pytest.mark.parametrize("path, cmd", LEAVES, ids=[p for p, _ in LEAVES])
def test_every_command_that_logs_has_quiet(path, cmd):
    opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
    if path in REPORTS:
        return
    assert {"--quiet", "-q"} <= opts, f"needle {path}: no --quiet/-q"


# ---------------------------------------------------------------------------------------------- progress
def test_the_results_file_reports_its_progress(tmp_path):
    import h5py
    import numpy as np

    from needlecli.io.results import Group, write_atomic

    root = Group(data={"a": np.arange(200_000.0).reshape(400, 500), "g": Group(data={"b": np.ones((3, 4))})},
                 attrs={"format": 1})
    seen = []
    write_atomic(tmp_path / "r.h5", root, progress=lambda k, n: seen.append((k, n)))
    assert len(seen) >= 3 and seen[-1][0] == seen[-1][1]
    done = [k for k, _ in seen]
    assert done == sorted(done)  # never goes back
    with h5py.File(tmp_path / "r.h5") as f:
        assert float(f["a"][-1, -1]) == 199_999.0 and f["g/b"].shape == (3, 4)


def test_rendered_frames_and_characterize_sensor_report_progress(tmp_path):
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.sensors.imaging.characterize import characterize_sensors

    cfg, text = load_config("configs/examples/imaging_us2d.yaml", runs=1, overrides=["stop.depth=4"])
    phases: dict[str, list] = {}
    run_experiment(cfg, text, out=tmp_path / "r.h5", progress=lambda p, k, n: phases.setdefault(p, []).append((k, n)))
    assert {"truth", "sensor us2d", "results file"} <= set(phases), phases.keys()
    frames = phases["sensor us2d"]
    assert frames[-1][0] == frames[-1][1] > 1 and len(frames) == frames[-1][1]  # one step per frame
    seen = []
    characterize_sensors(cfg, repeats=2, progress=lambda p, k, n: seen.append((p, k, n)))
    assert seen and seen[-1][1] == seen[-1][2] and seen[-1][0] == "sensor us2d"


def test_quiet_shows_no_progress_bar(tmp_path):
    args = ["simulate", "configs/examples/imaging_us2d.yaml", "--runs", "1", "--set", "stop.depth=4",
            "--out", str(tmp_path / "r.h5")]
    loud = CliRunner().invoke(app, args)
    quiet = CliRunner().invoke(app, [*args, "--quiet"])
    assert loud.exit_code == 0 and quiet.exit_code == 0, (loud.output, quiet.output)
    assert "sensor us2d" in loud.stderr and "results file" in loud.stderr
    assert quiet.stderr.strip() == ""
