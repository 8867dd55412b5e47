"""Evaluation against ground truth: per query (:mod:`~planarloc.evaluation.queries`, the paper's
success thresholds), per stream frame (:mod:`~planarloc.evaluation.sequence`) and trajectory
errors computed by evo (:mod:`~planarloc.evaluation.trajectory`)."""
