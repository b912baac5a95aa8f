"""Thin training entry points (``python -m train.train_fim_ppo``)."""
