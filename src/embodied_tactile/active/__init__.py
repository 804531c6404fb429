"""Closed-loop active palpation (docs/reference/active.md): touch sources (simulator / recordings),
the palpation model of a trained run, policies (active, random, fixed order, single action),
the episode loop and its evaluation. This package is where simulator output, preprocessing
and the model meet (like the data module); ``sim`` stays free of torch."""
