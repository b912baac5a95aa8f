"""Thin training entry points (``python -m selenv.train.train_fim_ppo``)."""
