"""Learned components on top of ``selenv``: RL glue for MaskablePPO and policy-as-agent adapters.

``learned.fim_policy`` holds the permutation-equivariant candidate-scoring policy and the
MaskablePPO factory; ``learned.agent`` wraps a shipped checkpoint as the ``ppo`` agent.
Nothing in ``selenv`` imports this package except through lazy ``"module:attr"`` factories.
"""
