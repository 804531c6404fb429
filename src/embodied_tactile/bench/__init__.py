"""The pendulum benchmark outside the tactile scene (:mod:`.pendulum`, numpy only;
:mod:`.pendulum_run`, trained by the project's LightningModule and Trainer) and its
``--remedy`` options (:mod:`.remedies`), shared by ``benchmarks/`` and the tests."""
