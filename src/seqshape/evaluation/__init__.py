"""Evaluation of shape and pose estimates: metrics, the per-frame runner, reports, plots.

See docs/evaluation.md for exactly what is computed. :mod:`seqshape.evaluation.evaluate`
(``evaluate_dataset``, ``evaluate_to``) runs ``seqshape evaluate``: the methods, the scores and
every output file; it loads the networks, so it is not imported here: this package stays
torch-free for the EMD worker processes. Heavy third-party modules (matplotlib, plotly) are
imported only when used.
"""

from seqshape.evaluation.metrics import (
    cd_floor,
    chamfer_distance,
    earth_movers_distance,
    emd_subsampled,
    pose_errors,
    rotation_error,
    subsample,
    subsample_pair,
    translation_error,
)
from seqshape.evaluation.report import (
    PAPER_TABLE,
    breakdown,
    metrics_markdown,
    summarize,
    write_metrics,
)
from seqshape.evaluation.runner import (
    EvalResult,
    detection_span,
    estimate_extents,
    evaluate_tracks,
    predict_track,
    radial_tangential,
)

__all__ = ["PAPER_TABLE", "EvalResult", "breakdown", "cd_floor", "chamfer_distance",
           "detection_span", "earth_movers_distance", "emd_subsampled", "estimate_extents",
           "evaluate_tracks", "metrics_markdown", "pose_errors", "predict_track",
           "radial_tangential", "rotation_error", "subsample", "subsample_pair", "summarize",
           "translation_error", "write_metrics"]
