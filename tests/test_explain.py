"""needle explain: the config reference read from the schema: sections, components, nested keys, input
kinds, errors with what is there, and the Markdown pages of the reference."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.explain import explain, reference_pages


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


# ------------------------------------------------------------------------ every key, documented and explained
def _schemas_of(annotation):
    """The pydantic schemas a field's type holds (through Optional, lists, dict values, unions)."""
    import typing

    from pydantic import BaseModel

    while typing.get_origin(annotation) is typing.Annotated:
        annotation = typing.get_args(annotation)[0]
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in typing.get_args(annotation) for m in _schemas_of(a)]


def _tag(schema, others):
    """The value of the key (a one-value Literal) that tells this schema from the others of its union."""
    import typing

    for name in schema.model_fields:
        vals = []
        for m in others:
            f = m.model_fields.get(name)
            t = f.annotation if f is not None else None
            if t is None or typing.get_origin(t) is not typing.Literal:
                break
            vals.append(typing.get_args(t)[0])
        else:
            if len(set(vals)) == len(others):
                return str(typing.get_args(schema.model_fields[name].annotation)[0])
    raise AssertionError(f"{schema.__name__}: no key tells the union's members apart")


def _key_paths():
    """Every key of the whole schema as `needle explain` names it: walked here from the pydantic models
    and the registries themselves, not from explain's own walk."""
    from needlecli.control import CONTROLLERS
    from needlecli.experiments.config import schedule
    from needlecli.experiments.config.schema import _model_spec, experiment_schema
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.sensors import SENSORS

    out = []

    def walk(schema, prefix):
        assert prefix.count(".") < 12, prefix  # the schema is a tree, not a cycle
        for name, info in schema.model_fields.items():
            key = f"{prefix}.{info.alias or name}"
            out.append(key)
            subs = _schemas_of(info.annotation)
            for m in subs:
                walk(m, key if len(subs) == 1 else f"{key}.{_tag(m, subs)}")

    root = experiment_schema()
    regs = {"model": MODELS, "sensors": SENSORS, "observers": OBSERVERS, "control": CONTROLLERS}
    for name, info in root.model_fields.items():
        out.append(name)
        if name in regs:
            for t, cls in regs[name].loaded().items():
                walk(_model_spec(t, cls) if name == "model" else cls.Settings, f"{name}.{t}")
        elif name == "inputs":
            kinds = _schemas_of(schedule.Signal)
            for m in kinds:
                walk(m, f"inputs.{_tag(m, kinds)}")
        else:
            for m in _schemas_of(info.annotation):
                walk(m, name)
    return out


def test_no_key_of_the_schema_lacks_a_description():
    from needlecli.experiments.config.explain import undocumented

    assert undocumented() == []


def test_needle_explain_covers_every_key_with_its_description():
    paths = _key_paths()
    assert len(paths) > 350 and "sensors.position.image.us3d.voxel" in paths and "inputs.cases.cases.flips.rate" in paths
    pages = "\n".join(reference_pages().values())
    missing, bare, unpaged = [], [], []
    for path in paths:
        parent, _, key = path.rpartition(".")
        try:
            explain(path)  # the key itself (a value's line, or the section below it)
            sec = explain(parent or None)  # and the section that lists it
        except ConfigError as e:
            missing.append(f"{path}: {e}")
            continue
        hit = [f for f in sec.fields if f.name == key]
        if not hit:
            missing.append(path)
        elif not hit[0].description and not (key in ("type", "kind") and parent):
            bare.append(path)
        if parent and f"`{parent}`" not in pages:
            unpaged.append(parent)
    assert not missing, missing[:20]
    assert not bare, bare[:20]
    assert not sorted(set(unpaged)), sorted(set(unpaged))[:20]


# ------------------------------------------------------------------------ the CSV mapping of needle log import-csv
def _mapping_paths():
    """Every key of the CSV mapping as `needle explain` names it (``mapping.sensors.quaternion.tol``: the
    values of a name -> section mapping are described at the mapping's own key), walked here from the
    pydantic model itself."""
    from needlecli.io.csv_import import Mapping

    out = []

    def walk(schema, prefix):
        assert prefix.count(".") < 8, prefix
        for name, info in schema.model_fields.items():
            key = f"{prefix}.{info.alias or name}"
            out.append(key)
            for m in _schemas_of(info.annotation):
                walk(m, key)

    walk(Mapping, "mapping")
    return out


def test_needle_explain_covers_every_mapping_key_with_its_description():
    from needlecli.experiments.config.explain import mapping_page
    from needlecli.experiments.config.schema import experiment_schema

    assert "mapping" not in experiment_schema().model_fields  # the word names the mapping, never a config key
    paths = _mapping_paths()
    names = {p.rsplit(".", 1)[1] for p in paths}
    assert len(names) >= 44 and {"quaternion", "sigma_column", "leading_invalid", "valid_column", "meta_file"} <= names
    page = mapping_page()
    missing, bare = [], []
    for path in paths:
        parent, _, key = path.rpartition(".")
        try:
            explain(path)
            sec = explain(parent)
        except ConfigError as e:
            missing.append(f"{path}: {e}")
            continue
        hit = [f for f in sec.fields if f.name == key]
        if not hit:
            missing.append(path)
        elif not hit[0].description:
            bare.append(path)
        assert (f"# `{parent}`" if parent != "mapping" else "# `mapping`") in page, parent
        assert f"| `{key}` |" in page, path
    assert not missing, missing[:20]
    assert not bare, bare[:20]


def test_explain_mapping_in_the_terminal_and_as_markdown(tmp_path):
    r = invoke("explain", "mapping")
    assert r.exit_code == 0 and "needle log import-csv" in r.output and "sensors:" in r.output and "[required]" in r.output
    r = invoke("explain", "mapping.sensors.quaternion")
    assert r.exit_code == 0 and "tol: number  [default 0.05]" in r.output and "scalar part" in r.output
    r = invoke("explain", "mapping.sensors.quaternoin")
    assert r.exit_code == 2 and "[mapping -> sensors -> quaternoin] no key 'quaternoin' here" in r.output
    assert "did you mean 'quaternion'" in r.output
    r = invoke("explain", "mapping.leading_invalid", "--format", "md")
    assert r.exit_code == 0 and "| `leading_invalid` | one of 'start', 'trim', 'keep' | `'start'` |" in r.output
    r = invoke("explain", "--format", "md", "--out", tmp_path / "ref")
    from needlecli.experiments.config.explain import mapping_page

    assert r.exit_code == 0 and (tmp_path / "ref" / "mapping.md").read_text() == mapping_page()
