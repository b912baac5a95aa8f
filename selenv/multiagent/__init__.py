"""PettingZoo environments: ``fim_selection_v0`` (``env()``, ``parallel_env()``, ``raw_env``)."""
