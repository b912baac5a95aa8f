"""Argument validation shared by the scenario configs (:mod:`selenv.scenarios.validation`).

The scenarios themselves (frozen configs, seeded generators, objectives) live in their family
folders: ``selenv.families.<family>.scenario``. They depend on :mod:`selenv.core` and this
validation only (no gymnasium, no torch).
"""
