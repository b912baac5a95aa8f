"""PettingZoo environments: ``fim_selection_v0`` and ``receiver_clustering_v1``.

Each has ``env()``, ``parallel_env()`` and ``raw_env``; its code is in its family folder.
"""
