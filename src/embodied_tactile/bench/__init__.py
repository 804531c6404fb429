"""Helpers the benchmarks in ``benchmarks/`` share: the pendulum benchmark outside the tactile
scene (:mod:`.pendulum`, numpy only; :mod:`.pendulum_run`), its ``--remedy`` options
(:mod:`.remedies`) and the training-step timing helpers (:mod:`.step`)."""
