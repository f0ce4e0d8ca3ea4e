"""Config validation: every mistake of the corpus is reported in one line with the file and key path;
the shipped configs validate; ``--set`` overrides; a good config round-trips."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.config.schema import experiment_schema

ROOT = Path(__file__).resolve().parents[1]
BAD = sorted((Path(__file__).parent / "bad_configs").glob("*.yaml"))
# sweeps: grids; real: replays of logs made by `make real` from data outside the repository (validated by
# tests/test_real_data.py against a freshly imported log)
# configs that replay logs a make target writes into results/ (make real, make owndata) are checked there
#: configs whose observers come from a tutorial's own package: validated with it installed, by the page's test
#: (tests/test_tutorials.py::test_own_observer_page_installs_and_runs runs the page's `needle validate`)
NEEDS_PLUGIN = {"configs/tutorials/own_observer.yaml"}
SHIPPED = sorted(p for p in (ROOT / "configs").glob("**/*.yaml") if "sweeps" not in p.parts and "real" not in p.parts
                 and "../../results/" not in p.read_text() and not p.name.endswith("_grid.yaml")  # grids: sweep files
                 and p.relative_to(ROOT).as_posix() not in NEEDS_PLUGIN)

GOOD = """\
name: good
description: a minimal valid experiment
model: {type: modified_unicycle, params: {kappa: 0.004, beta_cut: 0.05}, initial_state: {beta: 0.1}}
inputs:
  v: 1.0
  u: {kind: flips, at_depths: [2.5]}
tissue:
  layers:
    - {depth: 0, curvature: 0.004}
    - {depth: 3, curvature: 0.002}
process_noise: {std: {alpha: 0.001}}
sensors:
  - {type: position, rate: 1, sigma: 0.3, growth: {transducer: [0, 0, 90], a: 1, d_max: 80}}
  - {type: encoder, rate: 100, channels: [roll, depth], sigma: [0.0035, 0.01]}
  - {type: elastography, rate: 1}
observers:
  - {type: open_loop, init: {from: nominal, std: {alpha: 0.087}}, q: {kappa: 1.0e-6}}
runs: {count: 3, seed: 5}
stop: {depth: 5}
simulation: {dt: 0.01}
output: {covariance: diag, store_every: 5}
"""


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def expectation(path: Path) -> tuple[str, str]:
    """``# expect: <key path> | <substring>`` from the first line of a corpus file."""
    first = path.read_text(encoding="utf-8").splitlines()[0]
    assert first.startswith("# expect:"), f"{path.name}: first line must be '# expect: <key path> | <text>'"
    loc, _, sub = first[len("# expect:") :].partition("|")
    assert sub.strip(), f"{path.name}: the expectation has no message substring"
    return loc.strip(), sub.strip()


def error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("error: ")]


def assert_one_error(result, *must_contain: str) -> str:
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert result.stderr.strip() == lines[0]  # on stderr, not stdout
    for s in must_contain:
        assert s in lines[0], f"{s!r} not in {lines[0]!r}"
    return lines[0]


# ---------------------------------------------------------------------------------------------- corpus
def test_corpus_is_complete():
    assert len(BAD) >= 24
    for p in BAD:
        expectation(p)


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_config_is_reported(path: Path):
    """Every other command stops at the first problem (one line); needle validate lists every problem, one
    line each naming the config, the first the same."""
    loc, sub = expectation(path)
    line = assert_one_error(invoke("simulate", path, "--dry-run"), str(path), sub)
    r = invoke("validate", path)
    assert r.exit_code == 2 and "Traceback" not in r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert lines[0] == line.replace(" (and 1 more problem)", "").split(" (and ")[0], (lines, line)
    assert all(ln.startswith(f"error: {path}: ") for ln in lines), lines
    if loc:
        assert f"[{loc}]" in line, f"key path [{loc}] not in {line!r}"
    else:
        assert "[" not in line.split(str(path), 1)[1].split(":", 1)[0]
    for jargon in ("Value error", "union_tag", "discriminator", "function-after", "constrained-", "instance of"):
        assert jargon not in line


@pytest.mark.parametrize("path", BAD, ids=[p.stem for p in BAD])
def test_bad_config_raises_config_error(path: Path):
    loc, sub = expectation(path)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    e = info.value
    assert e.source == str(path)
    assert " -> ".join(str(p) for p in e.loc) == loc
    assert sub in e.message and "\n" not in str(e)


def test_yaml_syntax_error_names_the_line(tmp_path: Path):
    p = tmp_path / "broken.yaml"
    p.write_text("name: x\nmodel: {type: unicycle\ninputs: {v: 1}\nstop: {depth: 5}\n")
    line = assert_one_error(invoke("validate", p), "broken.yaml", "YAML syntax error at line")
    assert "line 2" in line  # where the unclosed mapping starts


def test_missing_file(tmp_path: Path):
    assert_one_error(invoke("validate", tmp_path / "nope.yaml"), "nope.yaml", "no such file")


def test_validate_several_files(tmp_path: Path):
    good = tmp_path / "good.yaml"
    good.write_text(GOOD)
    bad = BAD[0]
    result = invoke("validate", good, bad)
    assert result.exit_code == 2
    assert f"ok: {good}" in result.stdout
    assert len(error_lines(result.stderr)) == 1 and str(bad) in result.stderr


# ---------------------------------------------------------------------------------------------- shipped configs
@pytest.mark.skipif(not SHIPPED, reason="no configs/**/*.yaml yet")
@pytest.mark.parametrize("path", SHIPPED, ids=[str(p.relative_to(ROOT)) for p in SHIPPED])
def test_shipped_config_validates(path: Path):
    result = invoke("validate", path)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == f"ok: {path}"
    # a shipped config may be warned about (a state its sensors do not see), never refused
    assert all(ln.startswith(f"warning: {path}: ") for ln in result.stderr.splitlines()), result.stderr


# ---------------------------------------------------------------------------------------------- good config
@pytest.fixture
def good(tmp_path: Path) -> Path:
    p = tmp_path / "good.yaml"
    p.write_text(GOOD)
    return p


def test_good_config_validates(good: Path):
    result = invoke("validate", good)
    assert result.exit_code == 0, result.output
    assert result.output.strip() == f"ok: {good}"


def test_good_config_round_trips(good: Path):
    cfg, text = load_config(good)
    assert text == GOOD  # the raw text is what the results file stores
    dumped = yaml.safe_dump(cfg.model_dump(mode="json", by_alias=True), sort_keys=False)
    again, _ = load_config(text=dumped)
    assert again == cfg
    # the whole schema (every registered type) reads it the same as the schema of the types it names
    assert experiment_schema().model_validate(yaml.safe_load(dumped)).model_dump() == cfg.model_dump()
    # the defaults are filled in and typed
    assert cfg.observers[0].init.from_ == "nominal"
    assert cfg.sensors[2].name is None and cfg.sensors[2].pipeline == "gaussian"
    assert cfg.output.covariance == "diag" and cfg.output.store_every == 5


def test_minimal_config_defaults():
    cfg, _ = load_config(text="model: {type: unicycle}\ninputs: {v: 1}\nstop: {time: 2}\n")
    assert cfg.name == "experiment" and cfg.runs.count == 1 and cfg.runs.seed == 0
    assert cfg.simulation.dt == 0.01 and cfg.sensors == [] and cfg.observers == []
    assert cfg.inputs["v"].kind == "constant" and cfg.inputs["v"].value == 1


# ---------------------------------------------------------------------------------------------- --set
def test_set_overrides(good: Path):
    cfg, text = load_config(
        good,
        overrides=["sensors.0.rate=2", "runs.count=7", "name=other", "output.covariance=full",
                   "inputs.u.at_depths=[1, 2]", "simulation.dt = 0.005"],
    )
    assert cfg.sensors[0].rate == 2 and cfg.runs.count == 7 and cfg.name == "other"
    assert cfg.output.covariance == "full" and list(cfg.inputs["u"].at_depths) == [1, 2]
    assert cfg.simulation.dt == 0.005
    # the text stored with the results is the overridden config
    again, _ = load_config(text=text)
    assert again == cfg
    # runs / seed options take precedence over the file
    cfg2, _ = load_config(good, runs=4, seed=9)
    assert (cfg2.runs.count, cfg2.runs.seed) == (4, 9)


def test_set_creates_missing_sections(good: Path):
    cfg, _ = load_config(good, overrides=["model.param_std.kappa=0.0001"])
    assert cfg.model.param_std == {"kappa": 0.0001}


def test_set_on_the_command_line(good: Path):
    result = invoke("validate", good, "--set", "sensors.1.rate=50", "--set", "runs.seed=1")
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(
    "override, loc, sub",
    [
        ("sensors.0.rate=-1", "[sensors -> 0 -> rate]", "greater than 0"),
        ("sensors.0.rate=fast", "[sensors -> 0 -> rate]", "should be a number, not a string"),
        ("sensors.7.rate=1", "[sensors -> 7]", "no such list entry"),
        ("runs.cout=3", "[runs -> cout]", "unknown key"),
        ("name.first=x", "[name]", "is not a mapping"),
        ("model.type=bicycle", "[model -> type]", "unknown type 'bicycle'"),
        ("runs.count", "", "is not of the form key.path=value"),
        ("stop.time=3", "[stop]", "exactly one of depth, time"),
    ],
)
def test_bad_override_is_reported(good: Path, override: str, loc: str, sub: str):
    line = assert_one_error(invoke("validate", good, "--set", override), str(good), sub)
    assert loc in line


def test_bad_override_in_simulate(good: Path, tmp_path: Path):
    out = tmp_path / "out"
    result = invoke("simulate", good, "--set", "sensors.0.dropout=1", "--out", out / "r.h5", "--quiet")
    assert_one_error(result, str(good), "[sensors -> 0 -> dropout]", "less than 1")
    assert not out.exists() or not any(out.iterdir())


# ---------------------------------------------------------------------------------------------- validate: every problem
MISSPELT = """\
name: misspelt
model: {type: modified_unicycle, params: {kapa: 0.005}}
inputs: {v: 1.5}
sensors:
  - {name: us3d, type: position, rat: 1.0, sigma: 0.3}
  - {name: robot, type: encodr, rate: 100}
observers:
  - {name: ukf, type: ukff}
runs: {count: 10, seeed: 1}
stop: {depth: 80}
output: {tables: [sumary]}
"""

ACROSS = """\
format: 2
model: {type: modified_unicycle}
inputs: {v: 1.5, uu: 0}
process_noise: {std: {alpah: 0.1}}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3}
observers:
  - {name: ukf, type: ukf, measurements: {us3: {sigma: 0.3}}, q: {x: 1.0, bta: 2.0}}
stop: {depth: 80}
"""


def test_validate_lists_every_problem_with_did_you_mean(tmp_path: Path):
    bad, across, good = tmp_path / "misspelt.yaml", tmp_path / "across.yaml", tmp_path / "good.yaml"
    bad.write_text(MISSPELT)
    across.write_text(ACROSS)
    good.write_text(ACROSS.replace("uu: 0", "u: 0").replace("alpah", "alpha").replace("us3:", "us3d:").replace("bta", "beta"))
    r = invoke("validate", bad, across, good)
    assert r.exit_code == 2 and "more problem" not in r.output
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert all(ln.startswith(f"error: {bad}: ") or ln.startswith(f"error: {across}: ") for ln in err), err
    expected = [
        (bad, "[model -> params -> kapa] unknown key; did you mean 'kappa'?"),
        (bad, "[sensors -> 0 -> rate] required key is missing"),
        (bad, "[sensors -> 0 -> rat] unknown key; did you mean 'rate'?"),
        (bad, "[sensors -> 1 -> type] unknown type 'encodr'"),
        (bad, "[observers -> 0 -> type] unknown type 'ukff'"),
        (bad, "[runs -> seeed] unknown key; did you mean 'seed'?"),
        (bad, "[output -> tables] unknown table 'sumary'"),
        (across, "[inputs -> uu] model 'modified_unicycle' has no input 'uu'"),
        (across, "[process_noise -> std -> alpah] model 'modified_unicycle' has no state 'alpah'; did you mean 'alpha'?"),
        (across, "[observers -> 0 -> q -> bta] model 'modified_unicycle' has no state 'bta'; did you mean 'beta'?"),
        (across, "[observers -> 0 -> measurements -> us3] no sensor named 'us3'; sensors: us3d; did you mean 'us3d'?"),
    ]
    assert len(err) == len(expected), err
    for (path, text), line in zip(expected, err):
        assert line.startswith(f"error: {path}: {text}"), (line, text)
    for word, meant in (("encodr", "encoder"), ("ukff", "ukf"), ("sumary", "summary")):
        assert any(f"'{word}'" in ln and ln.endswith(f"did you mean '{meant}'?") for ln in err), (word, err)
    assert r.stdout.strip() == f"ok: {good}"


def test_other_commands_give_the_first_problem_in_one_line(tmp_path: Path):
    bad = tmp_path / "misspelt.yaml"
    bad.write_text(MISSPELT)
    line = assert_one_error(invoke("simulate", bad, "--quiet"), str(bad))
    assert line == (f"error: {bad}: [model -> params -> kapa] unknown key; did you mean 'kappa'? (and 6 more problems)")
    with pytest.raises(ConfigError, match="did you mean 'kappa'"):
        load_config(bad)
