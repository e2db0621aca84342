"""``morph-sweep``: training runs on Ray Tune (``spec``: what runs; ``tune_run``: the trials; ``cli``: the tool)."""
