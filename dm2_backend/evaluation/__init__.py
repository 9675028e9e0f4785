"""Trajectory evaluation: APE/RPE through evo, the Freiburg relations metric, the DeepMapping2 paper's ATE,
and reports (terminal table, JSON, CSV, Markdown, plots, evo result archives)."""

from dm2_backend.evaluation.ape_rpe import MetricResult, PoseErrors, evaluate_poses
from dm2_backend.evaluation.paper_ate import PaperATE, paper_ate
from dm2_backend.evaluation.relations import RelationsResult, load_relations, relations_error

__all__ = [
    "MetricResult",
    "PaperATE",
    "PoseErrors",
    "RelationsResult",
    "evaluate_poses",
    "load_relations",
    "paper_ate",
    "relations_error",
]
