"""Experiments, in three rooms by role, each importing only the ones before it:

* :mod:`~needlecli.experiments.config`: what an experiment is -- the typed config
  (:class:`~needlecli.experiments.config.ExperimentConfig`), its schema assembled from the registries,
  loading with ``--set`` overrides and ``from_fit``, the checks across sections, the memory budget, input
  schedules, the logs a ``source:`` names, and ``needle explain``;
* :mod:`~needlecli.experiments.simulation`: the insertions -- the truth simulated (open or closed loop) or
  replayed from logs, measured by the sensors, the observers run on them, the results file;
* :mod:`~needlecli.experiments.studies`: studies over many of those -- ``needle compare``, ``crossval``,
  ``fit-em`` and ``sweep``.
"""
