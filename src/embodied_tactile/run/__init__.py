"""Run plumbing: the run folder, provenance, resume, settings checks, threads, summaries, the
typed configs registered for Hydra and where configs/ is."""
