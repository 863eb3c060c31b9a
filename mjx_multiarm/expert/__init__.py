"""The BiRRT expert: centralized RRT-Connect plans, decimated into environment actions.

``python -m mjx_multiarm.expert --help`` runs the batched precompute.
"""
