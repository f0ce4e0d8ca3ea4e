"""Tables and plots, built from results files only, registered by name in :data:`TABLES` and
:data:`PLOTS` (each module imported on first use: this package's import is light).

Table functions take the loaded results file and the errors of every observer and return a
``DataFrame`` (:mod:`.tables`); plot functions ``(results, errors, path_stem) -> Path | None``
(:mod:`.plots`).
"""

from needlecli.registry import Registry

_TABLE_MODULES = {
    "needlecli.reports.tables": ("summary", "accuracy", "status"),
    "needlecli.reports.seed003": ("pose_curvature_error", "prediction"),
    "needlecli.reports.seed000_001": ("x_pitch_roll_error", "rotation_convergence", "rotation_half_turns"),
    "needlecli.reports.seed004": ("fit_parameters", "mnm_parameters", "binm_parameters", "binm_vs_mnm", "fit_recovery",
                                  "fit_status"),
    "needlecli.reports.imaging": ("measurements",),
    "needlecli.reports.control": ("planar_control",),
    "needlecli.reports.consistency": ("consistency",),
    "needlecli.reports.identify": ("identifiability",),
    "needlecli.reports.real": ("real_tip_error", "measurement_use", "real_error_vs_depth", "per_trial",
                               "em_per_trial", "em_per_speed", "em_loglik"),
    "needlecli.reports.design": ("fit_by_design", "fit_regression", "fit_warnings"),
    "needlecli.reports.along_across": ("real_error_along_across",),
    "needlecli.reports.compare": ("compare", "compare_appendix"),
}
_PLOT_MODULES = {
    "needlecli.reports.plots": ("error_vs_depth", "trajectories"),
    "needlecli.reports.seed003": ("prediction", "curvature"),
    "needlecli.reports.seed000_001": ("rotation_error",),
    "needlecli.reports.seed004": ("fit_paths", "binm_singularity"),
    "needlecli.reports.imaging": ("imaging_frames",),
    "needlecli.reports.consistency": ("nees_vs_depth",),
    "needlecli.reports.design": ("fit_regression",),
    "needlecli.reports.along_across": ("error_along_across",),
}

#: the former names of tables and plots, named by the paper they reproduce (its alias, needlecli.papers),
#: and the names that say what they hold: a former name still finds its table (``--tables``,
#: ``output.tables``, a baseline), whose files take the current name
TABLE_ALIASES = {"seed000_table1": "x_pitch_roll_error", "seed001_convergence": "rotation_convergence",
                 "seed001_half_turns": "rotation_half_turns", "seed003_table1": "pose_curvature_error",
                 "seed004_table1": "mnm_parameters", "seed004_table2": "binm_parameters",
                 "seed004_table3": "binm_vs_mnm", "seed004_recovery": "fit_recovery"}
PLOT_ALIASES = {"seed001_rotation_error": "rotation_error", "seed004_fig5": "fit_paths",
                "seed004_fig10": "binm_singularity"}

#: the tables that read a fit file of ``needle fit-em`` (the others read results files); ``needle evaluate
#: FIT.h5`` writes those of :data:`FIT_DEFAULT` by default (the magnetic needle EM paper's tables
#: ``mnm_parameters``, ``binm_parameters``, ``binm_vs_mnm`` only for a fit of its models), the others when named
FIT_TABLE_NAMES = ("fit_parameters", "mnm_parameters", "binm_parameters", "binm_vs_mnm", "fit_recovery", "fit_status",
                   "identifiability", "fit_by_design", "fit_regression", "fit_warnings",
                   "em_per_trial", "em_per_speed", "em_loglik")
FIT_DEFAULT = FIT_TABLE_NAMES[:10]

#: table functions ``(results, errors) -> DataFrame``
TABLES: Registry = Registry("table", group="needlecli.tables", base=callable,
                            builtins={n: m for m, names in _TABLE_MODULES.items() for n in names}, aliases=TABLE_ALIASES)
#: plot functions ``(results, errors, path_stem) -> Path | None`` (None: not applicable to this file)
PLOTS: Registry = Registry("plot", group="needlecli.plots", base=callable,
                           builtins={n: m for m, names in _PLOT_MODULES.items() for n in names}, aliases=PLOT_ALIASES)

__all__ = ["FIT_DEFAULT", "FIT_TABLE_NAMES", "PLOTS", "PLOT_ALIASES", "TABLES", "TABLE_ALIASES"]
