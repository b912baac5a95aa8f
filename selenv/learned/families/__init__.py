"""Learning code that serves one family: its policies, scorers and labellers.

One module per family; clustering has two (``clustering`` and its edit scorer,
``clustering_edits``).
"""
