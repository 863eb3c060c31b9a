"""The reaching environment (:mod:`.reaching`), its observations, batching wrappers (task
banks, auto-reset, episode statistics, replays) and a scripted IK baseline.
"""
