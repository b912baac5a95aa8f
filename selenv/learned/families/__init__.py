"""Learning code that serves one family (its policies, scorers, views), one module per family."""
