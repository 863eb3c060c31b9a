"""The reaching environment and what runs it.

- :mod:`.reaching`: ``reset``/``step``, control, targets, rewards, termination.
- :mod:`.observation`: the decentralized observations and the networks' input features.
- :mod:`.shield`: safe execution (a team step certified before it runs).
- :mod:`.wrappers`: device task banks, auto-reset, episode statistics, replays.
- :mod:`.scripted`: the damped-least-squares IK baseline controller.
- :mod:`.brax_env`, :mod:`.jaxmarl_env`: the environment as a Brax ``Env`` and a JaxMARL
  ``MultiAgentEnv``.
"""
