"""Trained policies deployed: the policy file format and the closed-loop :class:`Planner`.
"""
