"""Problem definitions: frozen config dataclasses, seeded generators and their objectives.

Each paper family has its own module (imported on demand, nothing is re-exported here):

* :mod:`selenv.scenarios.kirchner_models`: motion model (eq. 18) and the TOA (20), Doppler (22)
  and camera (23) measurement means and Jacobians of Kirchner, Hespanha & Garagić (2020).
* :mod:`selenv.scenarios.fim_selection`: their measurement-selection scenario (presets
  ``example1..3``, :class:`~selenv.scenarios.fim_selection.FIMProblem`).

Scenarios depend on :mod:`selenv.core` only (no gymnasium, no torch).
"""
