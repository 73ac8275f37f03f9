"""Accuracy evaluations: the paper's simulation (:mod:`hdmap.evaluation.paper_sim`)."""
