"""Flax networks: LSTM state encoder, actor, twin critics. A leaf: it imports nothing of the project (the observation features come in as a constructor argument)."""
