"""The insertions of an experiment: the truth simulated (open loop, or closed through controllers) or
replayed from recorded logs, measured by every sensor, the observers run on the same problem, and the
results file (:mod:`.runner`)."""
