"""Accuracy evaluations: the paper's simulation (:mod:`fleetsim.evaluation.paper_sim`)."""
