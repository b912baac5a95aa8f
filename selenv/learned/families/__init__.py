"""Learning code that serves one family (its policies, scorers, labellers): a module per family
(two for clustering: `clustering` and its edit scorer, `clustering_edits`)."""
