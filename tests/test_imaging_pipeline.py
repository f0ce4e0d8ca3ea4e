"""The ``image`` pipeline in experiments: config checks, the same clock and channels as the Gaussian
pipeline, extras and frames in the results file, the frame plot and error tables, characterize-sensor."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment

US3D = """\
name: tiny_us3d
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3, pipeline: image,
     image: {device: us3d, save_frames: 2, save_runs: 1}}
  - {name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035}
observers:
  - {name: ol, type: open_loop}
runs: {count: 2, seed: 3}
stop: {depth: 6.0}
"""

US2D = """\
name: tiny_us2d
model: {type: unicycle, params: {kappa: 0.0019}, initial_state: {gamma: 0.0524}}
inputs: {v: 2.0, u: 0.0}
sensors:
  - {name: us2d, type: position, rate: 10.0, axes: [x, y], sigma: 0.1, pipeline: image,
     image: {device: us2d, save_frames: 1}}
runs: {count: 2, seed: 0}
stop: {depth: 3.0}
"""

CAMERA = """\
name: tiny_camera
model: {type: mnm, params: {c: 9.5}, initial_state: {hy: -1.0, By: -1.0}}
inputs: {v: 0.002, omega_B: [0.0, 0.0, 0.1]}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.0e-5, pipeline: image,
     image: {device: camera, save_frames: 1}}
  - {name: coils, type: bfield, rate: 18.0, sigma: 0.005}
runs: {count: 2, seed: 4}
stop: {time: 2.0}
"""


@pytest.mark.parametrize(
    "edit, loc, words",
    [
        ("pipeline: image, image: {device: camera}}", ("sensors", 0, "image"), "measures x, y, not z"),
        ("pipeline: gaussian, image: {device: us2d}}", ("sensors", 0, "image"), "only with pipeline: image"),
        ("pipeline: image}", ("sensors", 0, "image"), "required with pipeline: image"),
        ("pipeline: image, image: {device: us2d, pixle: 0.1}}", ("sensors", 0, "image", "pixle"), "unknown key"),
        ("pipeline: image, image: {device: xray}}", ("sensors", 0, "image", "device"), "unknown device"),
    ],
)
def test_image_settings_are_checked_with_key_paths(edit, loc, words):
    text = US2D.replace("axes: [x, y]", "axes: [x, y, z]" if "camera" in edit else "axes: [x, y]")
    text = text.replace("pipeline: image,\n     image: {device: us2d, save_frames: 1}}", edit)
    with pytest.raises(ConfigError) as e:
        load_config(text=text)
    assert e.value.loc == loc and words in e.value.message


def test_image_pipeline_only_for_position_sensors():
    text = US3D.replace("channels: [roll], sigma: 0.0035}", "channels: [roll], sigma: 0.0035, pipeline: image}")
    with pytest.raises(ConfigError) as e:
        load_config(text=text)
    assert e.value.loc[-1] == "pipeline"


def _gaussian(text: str) -> str:
    """The same experiment with the statistical pipeline."""
    data = yaml.safe_load(text)
    for s in data["sensors"]:
        if s.pop("image", None) is not None:
            s["pipeline"] = "gaussian"
    return yaml.safe_dump(data)


@pytest.mark.parametrize("text, sensor, m", [(US3D, "us3d", 3), (US2D, "us2d", 2), (CAMERA, "camera", 2)],
                         ids=["us3d", "us2d", "camera"])
def test_image_sensors_keep_the_clock_and_channels_of_the_gaussian_ones(tmp_path, text, sensor, m):
    cfg, raw = load_config(text=text)
    out = run_experiment(cfg, raw, out=tmp_path / "r.h5")
    cfg_g, raw_g = load_config(text=_gaussian(text))
    ref = run_experiment(cfg_g, raw_g, write=False)
    st, st_g = out.measurements[sensor], ref.measurements[sensor]
    assert st.value.shape == st_g.value.shape and st.value.shape[-1] == m
    assert np.array_equal(st.t, st_g.t) and st.names == st_g.names and st.attrs["pipeline"] == "image"
    assert np.isnan(st.value[~st.valid]).all() and np.isfinite(st.value[st.valid]).all()
    assert st.valid.mean() > 0.5
    truth = out.truth.model.tip_position(out.truth.states[:, st.index])[..., : m]
    err = np.abs(st.value - truth)[st.valid] * (1000.0 if out.truth.model.length_unit == "m" else 1.0)
    assert err.max() < 2.0  # mm
    with h5py.File(out.path) as f:
        g = f[f"measurements/{sensor}"]
        assert g["frames"].dtype == np.uint8 and g["frames"].shape[0] >= 1
        assert g["frame_tip"].shape[1] == (3 if sensor == "us3d" else 2)
        assert g["image_valid"].shape == st.valid.shape
        if sensor == "camera":
            assert g["opacity"].shape == st.valid.shape and g["bz_command"].shape == st.valid.shape
    if out.estimates:
        assert all(p.status.tolist() == ["ok"] * 2 for p in out.estimates.values())


def test_evaluate_draws_a_frame_per_sensor_and_tabulates_measurement_errors(tmp_path):
    from needlecli.io.results import read_results
    from needlecli.reports.plots import PLOTS
    from needlecli.reports.tables import TABLES

    cfg, raw = load_config(text=US3D)
    res = read_results(run_experiment(cfg, raw, out=tmp_path / "r.h5").path)
    png = PLOTS.get("imaging_frames")(res, {}, tmp_path / "tiny")
    assert png.name == "tiny_imaging_frames.png" and png.stat().st_size > 1000
    table = TABLES.get("measurements")(res, {}).set_index("Axis")
    assert list(table.index) == ["x", "y", "z"] and (table["Pipeline"] == "image").all()
    assert (table["Std [mm]"] < 1.0).all() and (table["Valid [%]"] > 50).all()


def test_characterize_sensor_writes_tables(tmp_path):
    cfg_path = tmp_path / "cam.yaml"
    cfg_path.write_text(CAMERA)
    r = CliRunner().invoke(app, ["characterize-sensor", str(cfg_path), "--repeats", "2", "--out", str(tmp_path / "c")])
    assert r.exit_code == 0, r.output
    assert "Heading [deg]" in r.output and "sigma" in r.output
    csv = (tmp_path / "c" / "tiny_camera_camera_characterization.csv").read_text().splitlines()
    assert csv[0].startswith("Depth below surface [mm],Heading [deg],N,Lost [%]") and len(csv) == 13
    r = CliRunner().invoke(app, ["characterize-sensor", str(cfg_path), "--sensor", "coils"])
    assert r.exit_code == 2 and "does not use pipeline: image" in r.output
