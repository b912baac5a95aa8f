"""Learned components on top of ``selenv``: RL glue for MaskablePPO and policy-as-agent adapters.

``selenv.learned.rl`` holds the RL glue (candidate-scoring policy, candidate views, multi-agent
parameter sharing, the training loop, the ``ppo`` agent adapter); ``selenv.learned.surrogates`` and
``selenv.learned.surrogate_data`` the LDMV / LPECMV fusion surrogates and their datasets.
Nothing in ``selenv`` imports this package except through lazy ``"module:attr"`` factories.
"""
