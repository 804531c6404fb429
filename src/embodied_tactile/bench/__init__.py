"""Standard benchmarks for the Latent Filter outside the tactile scene (numpy only)."""
