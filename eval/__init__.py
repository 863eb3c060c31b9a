"""Evaluation: `python -m eval.benchmark` (the paper's tables), `eval.latency`, `eval.runtime`."""
