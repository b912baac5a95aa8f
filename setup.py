"""Package list for setuptools: every ``selenv*`` package plus the mapped checkpoint data.

The shipped checkpoints live in the repository's top-level ``checkpoints/`` folder and install
as ``selenv.checkpoints`` (metadata and options are in pyproject.toml).
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["selenv", "selenv.*"]), "selenv.checkpoints"],
    package_dir={"selenv.checkpoints": "checkpoints"},
)
