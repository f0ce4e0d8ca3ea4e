"""What ``needle evaluate`` writes, as a reader sees it (issue 15, items 2 and 3): every registered plot of a
simulated and of a replayed results file (truth only at some frames) holds data in every panel, in one
colour per observer, with units and no blank band; plots that cannot be computed are not written and the
log says why once; every ``.tex`` table compiles; one number format per column; one form of run counts."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import matplotlib
import numpy as np
import pandas as pd
import pytest
import yaml
from report_checks import capture_figures, compile_tables, figure_problems, needs_pdflatex
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.logs import log_from_results, write_log
from needlecli.io.results import read_results
from needlecli.metrics import compute_errors
from needlecli.reports.evaluate import evaluate_results
from needlecli.reports.plots import PLOTS, draw_plots, observer_colour, observer_colours, observer_look
from needlecli.reports.seed004 import ALL_FIT_TABLES
from needlecli.reports.tables import TABLES, column_formatter, latex_escape, to_latex, to_markdown

SIM = """\
format: 2
name: reports_sim
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}, param_std: {kappa: 0.0005}}
inputs:
  v: 1.5
  u: {kind: cases, labels: [no rotation, 0.19 rad/s], cases: [0.0, 0.19]}
process_noise: {std: {x: 0.02, y: 0.02, z: 0.02, alpha: 2.0e-4, beta: 2.0e-4, gamma: 5.0e-3}}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3}
  - {name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035}
  - {name: swe, type: elastography, rate: 1.0, sigma: 0.001}
observers:
  - name: ukf
    type: ukf
    q: {x: 2.0e-2, y: 2.0e-2, z: 2.0e-2, alpha: 2.0e-4, beta: 2.0e-4, gamma: 5.0e-3, kappa: 2.0e-5}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    measurements:
      us3d: {sigma: 0.3, growth: {transducer: [0.0, 0.0, 90.0], a: 1.0, d_max: 80.0}}
      robot: {sigma: 0.0035}
      swe: {sigma: 0.001}
    init:
      std: {alpha: 0.0873, beta: 0.0873}
      first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z, gamma: robot.roll, kappa: swe.kappa}
    kappa_max: 0.05
    predict_at_depths: [5, 10]
  - {name: open_loop, type: open_loop, init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}}}
runs: {count: 4, seed: 5}
stop: {depth: 12}
output: {store_every: 5}
"""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("reports")
    cfg, text = load_config(text=SIM)
    return run_experiment(cfg, text, out=d / "sim.h5").path


@pytest.fixture(scope="module")
def replayed(sim, tmp_path_factory) -> Path:
    """The simulated runs as recorded trials with a tracker-like truth every 7th step (0.07 s: not the
    covariance's stride), replayed: truth exists only at those frames."""
    d = tmp_path_factory.mktemp("replay")
    write_log(d / "log.h5", log_from_results(read_results(sim), truth_every=7))
    data = yaml.safe_load(SIM)
    for k in ("inputs", "sensors", "stop", "process_noise"):
        data.pop(k)
    data["name"] = "reports_replay"
    data["source"] = {"logs": [str(d / "log.h5")]}
    cfg, text = load_config(text=yaml.safe_dump(data, sort_keys=False))
    return run_experiment(cfg, text, out=d / "replay.h5", base_dir=d).path


def title(fig) -> str:
    return fig._suptitle.get_text() if fig._suptitle is not None else fig.axes[0].get_title()


def _draw_all(path: Path, out: Path):
    with pytest.MonkeyPatch.context() as mp:
        figs = capture_figures(mp, render=False)
        res = read_results(path)
        written = draw_plots(res, compute_errors(res), out / "p")
    return res, figs, written


@pytest.fixture(scope="module")
def drawn(sim, replayed, tmp_path_factory):
    """Every registered plot of each file, drawn once: ``{name: (results, figures, paths)}``."""
    return {k: _draw_all(p, tmp_path_factory.mktemp(k)) for k, p in (("sim", sim), ("replayed", replayed))}


@pytest.mark.parametrize("which", ["sim", "replayed"])
def test_every_plot_holds_data_in_one_colour_per_observer(which, drawn):
    res, figs, written = drawn[which]
    names = {p.name.split("p_", 1)[1].rsplit(".", 1)[0] for p in written}
    assert {"error_vs_depth", "trajectories", "curvature", "rotation_error", "prediction", "nees_vs_depth"} <= names, names
    assert len(figs) == len(written)
    colours = observer_colours(res)
    assert colours == {"open_loop": observer_colour("open_loop"), "ukf": observer_colour("ukf")}  # by name
    problems = [p for fig in figs for p in figure_problems(fig, colours, layout=which == "sim")]  # the same layout
    assert not problems, "\n".join(problems)
    # the same observer has the same colour in every figure (and in every panel: figure_problems)
    seen = {}
    for fig in figs:
        for ax in fig.axes:
            for ln in ax.lines:
                if (ln.get_gid() or "").startswith("observer:"):
                    seen.setdefault(ln.get_gid(), set()).add(ln.get_color())
    assert seen and all(len(c) == 1 for c in seen.values()), seen


@pytest.fixture(scope="module")
def second_study(tmp_path_factory) -> Path:
    """Another study: an EKF first (it sorts before the others in the results file), the open loop, the UKF
    with one prediction depth (as needle compare sets it)."""
    d = tmp_path_factory.mktemp("second")
    data = yaml.safe_load(SIM)
    ukf, ol = data["observers"]
    ukf["predict_at_depths"] = [3.0]
    ekf = {"name": "ekf", "type": "ekf", "q": dict(ukf["q"]), "p0": dict(ukf["p0"]), "init": dict(ukf["init"]),
           "measurements": {"us3d": {"sigma": 0.3}, "robot": {"sigma": 0.0035}, "swe": {"sigma": 0.001}}}
    data["observers"] = [ekf, ol, ukf]
    data["name"] = "reports_second"
    cfg, text = load_config(text=yaml.safe_dump(data, sort_keys=False))
    return run_experiment(cfg, text, out=d / "second.h5").path


def _looks(figs) -> dict[str, set]:
    """gid -> the (colour, dashes, marker) of every line drawn for it."""
    seen: dict[str, set] = {}
    for fig in figs:
        for ax in fig.axes:
            for ln in ax.lines:
                if (ln.get_gid() or "").startswith("observer:"):
                    seen.setdefault(ln.get_gid().split(":", 1)[1], set()).add(
                        (matplotlib.colors.to_hex(ln.get_color()), ln.get_marker()))
    return seen


def test_an_observer_keeps_its_colour_in_every_figure_of_every_study(drawn, second_study, tmp_path):
    """Two studies with their observers in different orders (and an EKF in one): every plot of both, and
    each observer is drawn in one colour and marker throughout, the one of its name."""
    first = drawn["sim"][1]
    res2, second, written = _draw_all(second_study, tmp_path)
    assert len(second) == len(written) >= 5
    looks = _looks(first + second)
    assert {"ukf", "open_loop", "ekf"} <= set(looks)
    for obs, seen in looks.items():  # single runs' thin lines go without markers
        assert {c for c, _ in seen} == {observer_colour(obs)}, (obs, seen)
        assert {m for _, m in seen} - {"None", "_"} == {observer_look(obs)["marker"]}, (obs, seen)  # _: error bar caps
    problems = [p for fig in second for p in figure_problems(fig, observer_colours(res2), layout=False)]
    assert not problems, "\n".join(problems)
    # one prediction depth: no plot of a single point (table prediction gives it)
    assert not [p for p in written if p.name.endswith("_prediction.png")]
    assert TABLES.get("prediction")(res2, compute_errors(res2)).shape[0] == 1


def test_curves_on_top_of_each_other_stay_visible():
    """The names that meet in one figure most often get different colours: the built-in observers' (also
    their default names and needle compare's), the built-in models' (fitted side by side), the bundled
    configs' tuned variants; any two observers differ in colour, dashes or marker, their markers start
    elsewhere, and none is the grey of sensor samples."""
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS

    # the Kalman family and the model alone (the particle filters join them in nine colours for nine types:
    # a name hash cannot promise that; rbpf shares the EKS's red and differs in dashes and marker, below)
    kalman = [n for n in OBSERVERS.builtin_names() if n not in ("pf", "rbpf")]
    for names in (kalman, MODELS.builtin_names(), ["ukf", "ukf_em", "ukf_em_white", "ukf_gated",
                  "open_loop"], ["hand_tuned", "em_tuned", "ukf_em"], ["ol", "ukf", "cv", "cv_kf"],
                  ["ukf_reset_1x", "ukf_reset_10x"], [*kalman, "ukf_defaults"]):
        assert len({observer_colour(n) for n in names}) == len(names), names
    names = OBSERVERS.builtin_names()
    more = [*names, "ukf_defaults"]  # every built-in type differs from every other in colour, dashes or marker
    assert len({(observer_colour(n), str(observer_look(n)["ls"]), observer_look(n)["marker"]) for n in more}) == len(more)
    assert observer_colour("ukf") == "#1f77b4" and "#7f7f7f" not in {observer_colour(n) for n in names}
    looks = [observer_look(n) for n in [*names, "ukf_em", "ukf_reset_1x", "ukf_reset_10x", "hand_tuned", "cv"]]
    keys = [(lk["color"], str(lk["ls"]), lk["marker"]) for lk in looks]
    assert len(set(keys)) == len(keys)
    a, b = observer_look("ukf"), observer_look("ekf")
    assert a["ls"] != b["ls"] and a["markevery"][0] != b["markevery"][0]


def test_legends_sit_outside_the_data(drawn, second_study, tmp_path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    figs = drawn["sim"][1] + _draw_all(second_study, tmp_path)[1]
    for fig in figs:
        fig.set_dpi(30)
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        r = canvas.get_renderer()
        legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        for leg in legends:
            box = leg.get_window_extent(r)
            for ax in fig.axes:
                assert not box.overlaps(ax.get_window_extent(r)), f"{title(fig)!r}: a legend over a panel"


def test_replayed_error_curves_come_from_the_truth_frames(drawn):
    """On a replay the mean over runs at grid times without truth is NaN: the curves are drawn at the
    frames where the truth exists (there every run has a sample)."""
    res, figs, _ = drawn["replayed"]
    fig = next(f for f in figs if "error against depth" in title(f))
    line = next(ln for ln in fig.axes[0].lines if ln.get_gid() == "observer:ukf")
    x, y = (np.asarray(a) for a in line.get_data())
    truth_steps = np.isfinite(res.data["truth"].data["state"][0, :, 0]).sum()
    assert len(x) == truth_steps and np.isfinite(y).all()
    es = compute_errors(res)["ukf"].quantities["E_xyz"]
    frames = np.nonzero(np.isfinite(es.values).all(0))[0]
    np.testing.assert_allclose(y, es.values[:, frames].mean(0))


def test_trajectories_draw_the_truth_they_list(drawn):
    _, figs, _ = drawn["replayed"]
    fig = next(f for f in figs if "tip paths" in title(f))
    truth = [ln for ax in fig.axes for ln in ax.lines if ln.get_gid() == "truth"]
    assert truth and all(np.isfinite(ln.get_xydata()).all() and len(ln.get_xydata()) > 10 for ln in truth)
    assert [t.get_text() for t in fig.legends[0].get_texts()][0].startswith("reference")
    assert all(ax.get_xlabel() == "z [mm]" for ax in fig.axes)


def test_titles_claim_only_what_is_drawn(drawn):
    """12 mm of an arc of radius 200 mm: no half turn is reached, none is claimed."""
    _, figs, _ = drawn["sim"]
    fig = next(f for f in figs if "rotation error" in title(f))
    assert "half turn" not in title(fig)
    assert not any("half turn" in t.get_text() for leg in fig.legends for t in leg.get_texts())


def test_a_plot_that_cannot_be_computed_is_not_written_and_the_log_says_why_once(sim, tmp_path, caplog):
    res = read_results(sim)
    res.data["truth"].data["state"] = np.full_like(res.data["truth"].data["state"], np.nan)  # no truth at all
    with caplog.at_level(logging.INFO, logger="needlecli"):
        written = draw_plots(res, compute_errors(res), tmp_path / "p")
    names = {p.name for p in written}
    assert "p_error_vs_depth.png" not in names and "p_rotation_error.png" not in names
    lines = [r.getMessage() for r in caplog.records if "error_vs_depth" in r.getMessage()]
    assert len(lines) == 1 and "not written" in lines[0] and "no error quantity" in lines[0]
    assert "p_trajectories.png" in names  # the estimates still have paths


# ---------------------------------------------------------------------------------------------- tables
def test_one_number_format_per_column():
    fmt = column_formatter([0.3593, 15.09, 0.0001992, np.nan])
    assert [fmt(v) for v in (0.3593, 15.09, 0.0001992, np.nan)] == ["0.3593", "15.09", "0.0001992", "n/a"]
    fmt = column_formatter([2e-14, 0.02, 0.5])  # spans too much for fixed point: all scientific
    assert [fmt(v) for v in (2e-14, 0.02, 0.5)] == ["2.000e-14", "2.000e-02", "5.000e-01"]
    fmt = column_formatter([5.0, 10.0, 40.0])
    assert [fmt(v) for v in (5.0, 10.0, 40.0)] == ["5", "10", "40"]
    md = to_markdown(pd.DataFrame({"a": [1e-5, 0.3]}))
    assert "1.000e-05" in md and "3.000e-01" in md


def test_latex_escapes_names_headers_and_captions():
    df = pd.DataFrame({"E_x,y,z (mm)": [0.5], "Gated [% of valid]": [1.0], "Observer": ["open_loop"]})
    tex = to_latex(df, caption="E_xyz of open_loop: 5 % & more, ± 1 #", label="tab:a_b")
    assert r"E\_x,y,z" in tex and r"open\_loop" in tex and r"\% of valid" in tex and r"$\pm$" in tex
    assert tex.splitlines()[0] == r"% needlecli table; needs \usepackage{booktabs}"
    assert latex_escape("a_b^c~{d}") == r"a\_b\textasciicircum{}c\textasciitilde{}\{d\}"


def _results_tables():
    return [n for n in TABLES.names() if n not in ALL_FIT_TABLES]


@needs_pdflatex
def test_every_latex_table_of_a_run_compiles(sim, replayed, tmp_path):
    tex = []
    for path in (sim, replayed):
        evaluate_results(path, tables=_results_tables(), out_dir=tmp_path / path.stem, formats=["tex", "md"])
        tex += sorted((tmp_path / path.stem).glob("*.tex"))
    assert len(tex) == 2 * len(_results_tables())
    compile_tables(tex, tmp_path)


def test_markdown_and_latex_say_the_same(sim, tmp_path):
    evaluate_results(sim, tables=["pose_curvature_error"], out_dir=tmp_path, formats=["md", "tex"])
    md = (tmp_path / "reports_sim_pose_curvature_error.md").read_text()
    tex = (tmp_path / "reports_sim_pose_curvature_error.tex").read_text()
    caption = md.split("\n\n")[0]
    assert "after initialisation" in caption
    assert latex_escape(caption) in tex
    cells = [c.strip() for c in md.splitlines()[4].split("|")[1:-1]]
    assert " & ".join(latex_escape(c) for c in cells) + r" \\" in tex
    # the summary counts the initial step too, and says so
    assert "the initial one included" in evaluate_results(sim, tables=["summary"])["summary"].attrs["caption"]


def test_run_counts_have_one_form(sim, replayed):
    for path in (sim, replayed):
        tables = evaluate_results(path, tables=_results_tables())
        for name, df in tables.items():
            for col in ("Runs", "Trials"):
                if col in df.columns and len(df):
                    assert df[col].astype(str).str.fullmatch(r"\d+/\d+").all(), (name, col, df[col].tolist())


def test_accuracy_is_named_for_what_it_is(sim):
    doc = TABLES.get("accuracy").__doc__
    assert "x_pitch_roll_error" in doc and "form of the high-gain observer paper" not in doc
    assert "The high-gain observer paper's Table I" in TABLES.get("x_pitch_roll_error").__doc__


def test_measurement_use_has_one_row_per_distinct_run(replayed, tmp_path):
    data = yaml.safe_load(read_results(replayed).attrs["config"])
    data["source"]["trials"] = ["run0000"] * 4  # one recorded trial, four times
    data["observers"] = [o for o in data["observers"] if o["name"] == "ukf"]
    cfg, text = load_config(text=yaml.safe_dump(data, sort_keys=False))
    out = run_experiment(cfg, text, out=tmp_path / "r.h5", base_dir=tmp_path).path
    df = evaluate_results(out, tables=["measurement_use"])["measurement_use"]
    assert len(df) == 3 and set(df["Channel"]) == {"us3d", "robot", "swe"}  # not 12 identical rows
    assert (df["Runs"] == "4/4").all() and (df["Trial"] == "run0000").all()


def test_fit_tables_are_refused_on_results_files(sim):
    r = invoke("evaluate", sim, "--tables", "em_per_trial", "--no-plots")
    assert r.exit_code == 2 and "needs a fit file" in r.output


def test_every_plot_is_registered_once():
    assert len(PLOTS.names()) == len(set(PLOTS.names()))


# ---------------------------------------------------------------------------------------------- fit files
@pytest.fixture(scope="module")
def unicycle_fit(tmp_path_factory) -> Path:
    """The EM tutorial's unicycle, 3 trials, a few EM iterations."""
    d = tmp_path_factory.mktemp("unicycle_fit")
    cfg = Path(__file__).resolve().parents[1] / "configs" / "tutorials" / "fit_em.yaml"
    r = invoke("fit-em", cfg, "--out", d / "fit.h5", "--quiet", "--set", "runs.count=3", "--set", "fit.em.max_iter=3",
               "--set", "fit.identify.enabled=false", "--set", "fit.repeats=2")
    assert r.exit_code == 0, r.output
    return d / "fit.h5"


def test_a_fit_of_another_model_gets_tables_named_for_what_they_hold(unicycle_fit, tmp_path):
    """A unicycle's fit writes fit_parameters and fit_recovery, not the magnetic needle EM paper's tables of the MNM and BiNM
    (empty, captioned with the paper's numbers, as it used to); those are still there by name."""
    r = invoke("evaluate", unicycle_fit, "--out", tmp_path / "t", "--no-plots")
    assert r.exit_code == 0, r.output
    written = sorted(p.name for p in (tmp_path / "t").glob("*.csv"))
    assert not [n for n in written if "seed" in n or "mnm" in n], written
    for t in ("fit_parameters", "fit_recovery", "fit_status"):
        assert f"fit_em_{t}.csv" in written and f"## {t}" in r.output
    df = pd.read_csv(tmp_path / "t" / "fit_em_fit_parameters.csv")
    assert set(df["Model"]) == {"unicycle"} and "kappa" in set(df["Quantity"]) and "tr(R_tracker)" in set(df["Quantity"])
    with h5py.File(unicycle_fit) as f:  # the mean of the fitted constant over the kept trials
        kappa = f["fit/unicycle/constant/kappa"][()]
    assert float(df.loc[df["Quantity"] == "kappa", "Mean"].iloc[0]) == pytest.approx(kappa.mean(), rel=1e-6)
    r = invoke("evaluate", unicycle_fit, "--tables", "seed004_recovery", "--no-plots", "--out", tmp_path / "old")
    assert r.exit_code == 0 and (tmp_path / "old" / "fit_em_fit_recovery.csv").exists()  # a former name: the table's own


def test_the_log_likelihood_decrease_line_says_whether_it_matters():
    from types import SimpleNamespace

    from needlecli.cli.fit_em import ll_decrease_line

    ll = np.array([[-1000.0, -500.0, -100.0, -100.2, -90.0], [-800.0, -700.0, -650.0, np.nan, np.nan]])
    small = SimpleNamespace(ll_decreases=np.array([1, 0]), ll_worst_drop=np.array([0.2, 0.0]), history={"loglik": ll})
    line = ll_decrease_line(small)
    assert "in 1 iteration(s) of 1 trial(s)" in line and "0.022 % of its trial's rise" in line and "negligible" in line
    big = SimpleNamespace(ll_decreases=np.array([1, 2]), ll_worst_drop=np.array([0.2, 40.0]), history={"loglik": ll})
    line = ll_decrease_line(big)
    assert "in 3 iteration(s) of 2 trial(s)" in line and "27 % of its trial's rise" in line and "not negligible" in line
    assert ll_decrease_line(SimpleNamespace(ll_decreases=np.zeros(2, int), ll_worst_drop=np.zeros(2), history={})) == ""
