"""Flax networks: LSTM state encoder, actor, twin critics (issue 6)."""
