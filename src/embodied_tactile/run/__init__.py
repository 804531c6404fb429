"""Run plumbing: the training recipe (``training``) inside its run folder's lifecycle
(``lifecycle``, ``runfolder``), provenance, resume, threads, progress, settings checks,
summaries, the typed configs registered for Hydra and where configs/ is."""
