"""Studies over many insertions or experiments: every observer on the same insertions (``needle compare``,
:mod:`.compare`), held-out trials (:mod:`.crossval`), EM fits of recorded or simulated trials
(``needle fit-em``, :mod:`.fit`) and parameter sweeps (:mod:`.sweep`)."""
