"""Preparation, the paper's first stage: warm start -> map topology -> pairwise registration."""
