"""Evaluation: `python -m eval.benchmark`, paper tables, runtime, latency (issue 7)."""
