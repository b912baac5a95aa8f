"""The shipped checkpoints, installed as the data package ``selenv.checkpoints``.

Find a file with :func:`selenv.learned.resources.checkpoint_path` (``importlib.resources``),
never with a path relative to the source tree: the wheel has no ``checkpoints/`` folder.
"""
