"""needle explain: the config reference read from the schema: sections, components, nested keys, input
kinds, errors with what is there, and the Markdown pages of the reference."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.explain import explain, reference_pages


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.mark.parametrize("path, keys", [
    (None, ["name", "model", "sensors", "observers", "runs", "stop", "fit"]),
    ("sensors", ["name", "rate", "latency", "dropout", "pipeline"]),
    ("sensors.position", ["axes", "sigma", "growth"]),
    ("observers.ukf", ["q", "p0", "measurements", "init", "alpha"]),
    ("observers.ukf.init", ["from", "values", "std", "first_measurement"]),
    ("model.mnm", ["params", "param_std", "initial_state"]),
    ("model.mnm.params", ["c"]),
    ("inputs.flips", ["at_depths", "angle", "rate", "base"]),
    ("fit.em", ["max_iter", "tol", "accelerate"]),
    ("fit.identify", ["enabled", "rse_max", "nats"]),
    ("output.covariance", ["covariance"]),
])
def test_explain_names_the_keys(path, keys):
    sec = explain(path)
    names = [f.name for f in sec.fields]
    for k in keys:
        assert k in names, (path, names)


def test_sections_list_their_types_and_fields_say_what_they_are():
    assert {"position", "encoder", "elastography"} <= set(explain("sensors").choices)
    assert {"ukf", "ekf", "open_loop"} <= set(explain("observers").choices)
    assert {"flips", "piecewise", "cases"} <= set(explain("inputs").choices)
    rate = next(f for f in explain("sensors").fields if f.name == "rate")
    assert rate.default == "required" and "Hz" in rate.description and "> 0" in rate.constraints
    cov = explain("output.covariance").fields[0]
    assert cov.type == "one of 'full', 'diag', 'none'" and cov.default == "'full'"


@pytest.mark.parametrize("path, message", [
    ("sensor", "no key 'sensor' here"),
    ("observers.ukff", "no observer type 'ukff'; known: "),
    ("observers.ukf.inti", "no key 'inti' here; keys: "),
    ("inputs.flop", "no input kind 'flop'"),
])
def test_explain_errors_say_what_is_there(path, message):
    with pytest.raises(ConfigError, match=message):
        explain(path)
    r = invoke("explain", path)
    assert r.exit_code == 2 and message.split(";")[0] in r.output and "Traceback" not in r.output


def test_the_terminal_and_markdown_forms(tmp_path):
    r = invoke("explain", "observers.ukf")
    assert r.exit_code == 0 and "measurements:" in r.output and "[default" in r.output
    r = invoke("explain", "sensors", "--format", "md")
    assert r.exit_code == 0 and "| key | type | default | description |" in r.output and "| `position` |" in r.output
    r = invoke("explain", "--format", "md", "--out", tmp_path / "ref")
    assert r.exit_code == 0
    pages = reference_pages()
    assert set(pages) >= {"index", "model", "sensors", "observers", "inputs", "fit", "output"}
    assert "## `observers.ukf`" in pages["observers"] and "`observers.ukf.init`" in pages["observers"]
    assert (tmp_path / "ref" / "observers.md").read_text() == pages["observers"]
