"""Evaluation of runs, in evo's tiers: the pure scorers are core (:mod:`memgs_ros.core.metrics`:
PSNR/SSIM/LPIPS, ATE and rotation error on arrays), this package is the tools tier, and
``memgs eval`` (:mod:`memgs_ros.cli.evaluate`) is the CLI over it.

- :mod:`.runs`: score a finished run from its files; run + score; the ablation;
- :mod:`.timeline`: the run's stats timeline read back (map size, training rate, peak RSS);
- :mod:`.tables`: Markdown tables of results;
- :mod:`.plots`: trajectory, error, PSNR, map-size and frame-strip plots into an ``Axes``;
- :mod:`.figures`: the PNG files ``memgs eval`` writes from those plots.

Import from the modules themselves (``evaluation.runs`` imports torch; ``timeline`` does not).
"""
