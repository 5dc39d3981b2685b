"""Evaluation of a result folder against the simulator's ground truth.

`evaluate_result(truth_path, result_dir)` returns an `EvaluationReport`
(`to_dict()` for JSON, `table()` / `per_tree_table()` for rich). Metric
definitions: docs/results.md.
"""

from orchard_mapping.eval.evaluate import evaluate_result
from orchard_mapping.eval.ground_truth import GROUND_TRUTH_SCHEMA, GroundTruth, TrueSide, TrueTree, load_ground_truth
from orchard_mapping.eval.report import EvaluationReport

__all__ = [
    "GROUND_TRUTH_SCHEMA",
    "EvaluationReport",
    "GroundTruth",
    "TrueSide",
    "TrueTree",
    "evaluate_result",
    "load_ground_truth",
]
