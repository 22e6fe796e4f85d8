"""Evaluation of runs, in evo's tiers: the pure scorers are core (:mod:`memgs_ros.core.metrics`:
PSNR/SSIM/LPIPS, ATE and rotation error on arrays), this package is the tools tier, and
``memgs eval`` (:mod:`memgs_ros.cli.evaluate`) is the CLI over it.

- :mod:`.runs`: score a finished run from its files; run + score; the ablation;
- :mod:`.timeline`: the run's stats timeline read back (map size, training rate, peak RSS);
- :mod:`.tables`: Markdown tables of results;
- :mod:`.plots`: trajectory, error, PSNR, map-size and frame-strip plots into an ``Axes``;
- :mod:`.figures`: the PNG files ``memgs eval`` writes from those plots.

The names below are :mod:`.runs`' and :mod:`.timeline`'s public API (importing this package imports torch).
"""
from memgs_ros.evaluation.runs import (
    ABLATION_LABELS,
    ABLATION_VARIANTS,
    ATE_MAX_DT_S,
    FRAME_MATCH_MAX_DT_S,
    AblationResult,
    EvalResult,
    MemoryResult,
    QualityResult,
    TrajectoryResult,
    ablation,
    evaluate,
    evaluate_run,
    mode_edits,
    result_from_dict,
    run_edits,
    score_map,
    score_trajectory,
    write_json,
)
from memgs_ros.evaluation.timeline import MapSample, map_samples, node_peak_rss_mb, training_rate

__all__ = [
    "ABLATION_LABELS",
    "ABLATION_VARIANTS",
    "ATE_MAX_DT_S",
    "FRAME_MATCH_MAX_DT_S",
    "AblationResult",
    "EvalResult",
    "MapSample",
    "MemoryResult",
    "QualityResult",
    "TrajectoryResult",
    "ablation",
    "evaluate",
    "evaluate_run",
    "map_samples",
    "mode_edits",
    "node_peak_rss_mb",
    "result_from_dict",
    "run_edits",
    "score_map",
    "score_trajectory",
    "training_rate",
    "write_json",
]
