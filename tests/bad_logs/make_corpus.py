"""Builds the corpus of bad logs and CSV exports in this folder (run it to rebuild; the files are
committed). Each case is one small file with one mistake; ``expect.yaml`` says which command meets it
and what its one-line error must contain."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import yaml

HERE = Path(__file__).parent


def good_log(path: Path, n: int = 40, dt: float = 0.1) -> None:
    """A small valid log: 1 trial of the unicycle, position at 10 Hz, roll encoder, ground truth."""
    t = dt * np.arange(n)
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "needlecli-log"
        f.attrs["version"] = 1
        g = f.create_group("trials/t1")
        g.attrs["needle"] = "test"
        for name, val, unit in (("v", np.full(n, 2.0), "mm/s"), ("u", np.zeros(n), "rad/s")):
            s = g.create_group(f"inputs/{name}")
            s["t"] = t
            s["value"] = val
            s.attrs["unit"] = unit
        s = g.create_group("sensors/us")
        s["t"] = t
        s["value"] = np.stack([np.zeros(n), np.zeros(n), 2.0 * t], -1)
        s["valid"] = np.ones(n, bool)
        s.attrs["names"] = ["x", "y", "z"]
        s.attrs["units"] = ["mm", "mm", "mm"]
        s.attrs["sensor"] = json.dumps({"type": "position", "rate": 10.0, "sigma": 0.3})
        s = g.create_group("sensors/robot")
        s["t"] = t
        s["value"] = np.zeros((n, 1))
        s.attrs["names"] = ["roll"]
        s.attrs["units"] = ["rad"]
        s.attrs["sensor"] = json.dumps({"type": "encoder", "rate": 10.0, "channels": ["roll"], "sigma": 0.0035})
        s = g.create_group("truth")
        s["t"] = t
        s["state"] = np.stack([np.zeros(n), np.zeros(n), 2.0 * t, np.zeros(n), np.zeros(n), np.zeros(n)], -1)
        s.attrs["names"] = ["x", "y", "z", "alpha", "beta", "gamma"]
        s.attrs["units"] = ["mm", "mm", "mm", "rad", "rad", "rad"]


def edit(name: str, fn) -> str:
    path = HERE / f"{name}.h5"
    good_log(path)
    with h5py.File(path, "r+") as f:
        fn(f)
    return path.name


def main() -> None:
    for p in HERE.glob("*.h5"):
        p.unlink()
    for p in HERE.glob("*.csv"):
        p.unlink()
    for d in HERE.glob("csv_*"):
        shutil.rmtree(d)
    cases: dict[str, dict] = {}

    def case(file: str, expect: str, command: str = "replay"):
        cases[file] = {"command": command, "expect": expect}

    # --- HDF5 logs (replayed by a config through needle simulate, or checked by needle log info)
    good_log(HERE / "good.h5")
    p = HERE / "truncated.h5"
    p.write_bytes((HERE / "good.h5").read_bytes()[:3000])
    case(p.name, "cannot read the log")
    p = HERE / "garbage.h5"
    p.write_bytes(b"this is not an HDF5 file at all\n" * 10)
    case(p.name, "cannot read the log")
    p = HERE / "empty_file.h5"
    p.write_bytes(b"")
    case(p.name, "cannot read the log")

    def set_attr(key, value):
        return lambda f: f.attrs.__setitem__(key, value)

    case(edit("wrong_format", set_attr("format", "something-else")), "not a needlecli log")
    case(edit("newer_version", set_attr("version", 99)), "newer than this needlecli reads")
    case(edit("no_trials", lambda f: f.__delitem__("trials/t1")), "holds no trials")

    def rewrite(path_in, data):
        def fn(f):
            del f[path_in]
            f[path_in] = data
        return fn

    t_back = 0.1 * np.arange(40)
    t_back[17] = 1.0
    case(edit("time_backwards", rewrite("trials/t1/sensors/us/t", t_back)), "timestamps go backwards at sample 17")
    t_rep = 0.1 * np.arange(40)
    t_rep[9] = t_rep[8]
    case(edit("time_repeated", rewrite("trials/t1/sensors/us/t", t_rep)), "timestamp repeated at sample 9")
    t_nan = 0.1 * np.arange(40)
    t_nan[5] = np.nan
    case(edit("time_nan", rewrite("trials/t1/sensors/robot/t", t_nan)), "timestamp of sample 5 is not finite")
    v = np.stack([np.zeros(40), np.zeros(40), 0.2 * np.arange(40)], -1)
    v_nan = v.copy()
    v_nan[12, 1] = np.nan
    case(edit("nan_sample", rewrite("trials/t1/sensors/us/value", v_nan)), "sample 12 is marked valid but is not finite")
    v_inf = v.copy()
    v_inf[3, 0] = np.inf
    case(edit("inf_sample", rewrite("trials/t1/sensors/us/value", v_inf)), "sample 3 is marked valid but is not finite")
    case(edit("units_mismatch", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("units", ["m", "m", "m"])),
         "units ['m', 'm', 'm'] do not match ['mm', 'mm', 'mm']")
    case(edit("input_unit_mismatch", lambda f: f["trials/t1/inputs/v"].attrs.__setitem__("unit", "m/s")),
         "unit 'm/s' does not match the model's 'mm/s'")
    case(edit("names_count", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("names", ["x", "y"])),
         "[/trials/t1/sensors/us attribute units] has 3 names, but /trials/t1/sensors/us attribute names give m = 2")
    case(edit("missing_value", lambda f: f.__delitem__("trials/t1/sensors/us/value")), "missing dataset 'value'")
    case(edit("missing_time", lambda f: f.__delitem__("trials/t1/sensors/robot/t")), "missing dataset 't'")
    case(edit("shape_mismatch", rewrite("trials/t1/sensors/us/value", v[:30])), "[/trials/t1/sensors/us/value] has shape (30, 3), expected (M,) = (40,) or (M, m) = (40, 3)")
    case(edit("valid_shape", rewrite("trials/t1/sensors/us/valid", np.ones(39, bool))), "[/trials/t1/sensors/us/valid] has shape (39,), expected (M,) = (40,)")
    case(edit("bad_sensor_json", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("sensor", "{not json")),
         "attribute 'sensor' is not valid JSON")
    case(edit("sensor_without_type", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("sensor", "{}")),
         "must give the sensor's settings with its 'type'")
    case(edit("unknown_sensor_type", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("sensor", '{"type": "sonar", "rate": 1}')),
         "unknown sensor type 'sonar'")
    case(edit("bad_sensor_settings", lambda f: f["trials/t1/sensors/us"].attrs.__setitem__("sensor", '{"type": "position", "rate": -1}')),
         "settings: rate")
    case(edit("missing_sensors_group", lambda f: f.__delitem__("trials/t1/sensors")), "missing group 'sensors'")
    case(edit("missing_insertion_input", lambda f: f.__delitem__("trials/t1/inputs/v")), "missing input 'v'")
    case(edit("truth_shape", rewrite("trials/t1/truth/state", np.zeros((40, 4)))), "[/trials/t1/truth/state] has shape (40, 4), expected (L, n) = (40, 6)")
    case(edit("truth_nan", rewrite("trials/t1/truth/state", np.full((40, 6), np.nan))), "[trial t1 -> truth] sample 0 is not finite")
    case(edit("input_nan", rewrite("trials/t1/inputs/v/value", np.r_[np.full(10, 2.0), np.nan, np.full(29, 2.0)])),
         "[trial t1 -> input v] sample 10 is not finite")

    def second_trial_missing_channel(f):
        f.copy("trials/t1", "trials/t2")
        del f["trials/t2/sensors/robot"]

    case(edit("trial_missing_channel", second_trial_missing_channel), "missing channel 'robot'")

    # --- CSV exports (needle log import-csv MAPPING)
    def csv_case(name: str, us_csv: str, expect: str, mapping_edit=None, robot_csv: str | None = None):
        d = HERE / f"csv_{name}"
        d.mkdir()
        (d / "us.csv").write_text(us_csv)
        (d / "robot.csv").write_text(robot_csv or "t,speed\n0,2\n1,2\n2,2\n")
        mapping = {
            "trials": [{"id": "a", "dir": "."}],
            "inputs": {"v": {"file": "robot.csv", "column": "speed", "unit": "mm/s"}},
            "sensors": {"us": {"file": "us.csv", "columns": {"x": "tx", "y": "ty", "z": "tz"}, "units": ["mm", "mm", "mm"],
                               "sensor": {"type": "position", "rate": 1.0, "sigma": 0.3}}},
        }
        if mapping_edit:
            mapping_edit(mapping)
        (d / "mapping.yaml").write_text(yaml.safe_dump(mapping, sort_keys=False))
        cases[f"{d.name}/mapping.yaml"] = {"command": "import-csv", "expect": expect}

    good = "t,tx,ty,tz\n0,0,0,0\n1,0,0,2\n2,0,0,4\n"
    csv_case("bad_row", "t,tx,ty,tz\n0,0,0,0\n1,0,oops,2\n2,0,0,4\n", "[line 3, column ty] 'oops' is not a number")
    csv_case("short_row", "t,tx,ty,tz\n0,0,0,0\n1,0,0\n", "[line 3] has 3 fields, the header has 4")
    csv_case("missing_column", "t,tx,ty\n0,0,0\n", "[column tz] not in the header")
    csv_case("time_backwards", "t,tx,ty,tz\n0,0,0,0\n2,0,0,2\n1,0,0,4\n", "[line 4] time goes backwards")
    csv_case("time_repeated", "t,tx,ty,tz\n0,0,0,0\n1,0,0,2\n1,0,0,4\n", "[line 4] time repeated")
    csv_case("empty_csv", "", "the CSV is empty")
    csv_case("unit_not_convertible", good, "unit 'kg' does not convert to 'mm'",
             lambda m: m["sensors"]["us"].__setitem__("units", ["kg", "mm", "mm"]))
    csv_case("input_unit_not_convertible", good, "unit 'furlong/s' does not convert to 'mm/s'",
             lambda m: m["inputs"]["v"].__setitem__("unit", "furlong/s"))
    csv_case("missing_file", good, "no such CSV file", lambda m: m["sensors"]["us"].__setitem__("file", "nope.csv"))
    csv_case("unknown_mapping_key", good, "[sensors -> us -> colums] unknown key",
             lambda m: m["sensors"]["us"].__setitem__("colums", {}))
    csv_case("unknown_sensor", good, "unknown sensor type 'sonar'",
             lambda m: m["sensors"]["us"]["sensor"].__setitem__("type", "sonar"))
    csv_case("channel_without_column", good, "no column for channel 'z'",
             lambda m: (m["sensors"]["us"]["columns"].pop("z"), m["sensors"]["us"].__setitem__("units", ["mm", "mm"])))

    (HERE / "expect.yaml").write_text(
        "# bad logs and CSV exports: the command that meets each, and what its one-line error contains\n"
        + yaml.safe_dump(cases, sort_keys=True, width=200)
    )


if __name__ == "__main__":
    main()
