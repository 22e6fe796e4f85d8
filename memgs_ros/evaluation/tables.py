"""Markdown tables of evaluation results for ``memgs eval`` (the results themselves come from
:mod:`memgs_ros.evaluation.runs`, which knows nothing of their layout).

Imports the results module (and so torch): ``memgs eval`` loads it only when it runs, never for
``memgs --help``.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

from memgs_ros.evaluation.runs import ABLATION_LABELS, FRAME_MATCH_MAX_DT_S, AblationResult, EvalResult

__all__ = ["TABLE_HEADER", "ablation_json", "ablation_table", "markdown_row", "markdown_table"]

TABLE_HEADER = ("| method | PSNR dB / Mem GB / Points k | model MB | PSNR valid px dB | PSNR kf dB | SSIM "
                "| LPIPS | ATE cm | rot deg | track FPS | map it/s | frames | KF |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|")
TABLE_FOOTNOTE_SPEED = ("track FPS: 1 / mean tracker time per frame; map it/s: mapping iterations per second "
                        "while training (mapper stats), whole-run rate in eval.json.")


def _fmt(v: float | None, spec: str) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _pct(a: float, b: float) -> float | None:
    return None if b == 0 else 100.0 * (a - b) / b


def _memory_footnote(r: EvalResult) -> str:
    m = r.memory
    if m.cuda_max_allocated_bytes is not None:
        return "Mem: the mapper's torch.cuda.max_memory_allocated."
    if m.mapper_working_peak_bytes is not None:
        base = "" if m.mapper_rss_baseline_mb is None else f" of {m.mapper_rss_baseline_mb:.0f} MB"
        return ("Mem*: CPU run, the mapper's peak resident memory above its start-up baseline"
                f"{base} (imports, node and compiled kernels), VmHWM read 10 times a second.")
    return "Mem*: CPU run, map parameters + gradients + Adam state at peak (no CUDA allocator)."


def markdown_row(r: EvalResult, label: str | None = None) -> str:
    """One row in the paper's layout (PSNR / Mem / Points) plus model MB, SSIM, ATE and speeds.
    Mem is the CUDA peak when the mapper had a GPU, else its peak RSS above the start-up
    baseline (marked ``*``; ``MemoryResult.headline_bytes``)."""
    mem = r.memory.headline_bytes / 1e9
    star = "" if r.memory.cuda_max_allocated_bytes is not None else "*"
    q, k = r.frames_quality, r.keyframes_quality
    ate_cm = None if r.trajectory is None else r.trajectory.rmse_m * 100.0
    rot = None if r.trajectory is None else r.trajectory.rotation_rmse_deg
    return (f"| {label or ABLATION_LABELS.get(r.variant, r.variant)} | {_fmt(q.psnr_db, '.2f')} / {mem:.3g}{star} / "
            f"{r.gaussians / 1000:.1f} | {r.memory.model_bytes_peak / 1e6:.1f} | {_fmt(q.psnr_db_valid, '.2f')} "
            f"| {_fmt(k.psnr_db, '.2f')} | {_fmt(q.ssim, '.3f')} | {_fmt(q.lpips, '.3f')} "
            f"| {_fmt(ate_cm, '.2f')} | {_fmt(rot, '.2f')} | {r.tracking_fps:.1f} "
            f"| {_fmt(r.mapping_iters_per_s_training, '.2f')} "
            f"| {q.n} | {k.n} |")


def markdown_table(results: Sequence[EvalResult], labels: Sequence[str] | None = None) -> str:
    """Header plus one row per result; a footnote says what the memory column is."""
    rows = [markdown_row(r, None if labels is None else labels[i]) for i, r in enumerate(results)]
    r0 = results[0] if results else None
    foot = ""
    if r0 is not None:
        foot = (f"\nPSNR/SSIM over every tracked frame matched to ground truth within {FRAME_MATCH_MAX_DT_S} s, "
                f"rendered at the mapping resolution {r0.render_size[0]}x{r0.render_size[1]} "
                f"(scale {r0.resolution_scale:g}); 'PSNR valid px': only pixels with image content after "
                "undistortion (same as the whole image without distortion); 'PSNR kf' on keyframes only. ATE: "
                f"{'Sim(3)' if r0.mode == 'mono' else 'SE(3)'} alignment; rot deg: RMSE of the rotation angle "
                "after the world rotation fitted to the orientations. "
                + _memory_footnote(r0) + " model MB: map parameters + gradients + Adam state at peak. "
                + TABLE_FOOTNOTE_SPEED)
    return TABLE_HEADER + "\n" + "\n".join(rows) + "\n" + foot + "\n"


def ablation_table(results: Sequence[EvalResult]) -> str:
    """Variants side by side with differences against the first (full MemGS): Gaussians %,
    memory %, PSNR dB (every frame and keyframes), ATE cm."""
    if not results:
        return ""
    base = results[0]
    lines = [markdown_table(results).rstrip("\n"), "",
             f"| variant | Gaussians vs {base.variant} | memory vs {base.variant} | PSNR dB | PSNR kf dB | ATE cm |",
             "|---|---|---|---|---|---|"]

    def diff(a: float | None, b: float | None, scale: float = 1.0) -> str:
        return ("n/a" if a is None or b is None or not (math.isfinite(a) and math.isfinite(b))
                else f"{(a - b) * scale:+.2f}")

    def ate(r: EvalResult) -> float | None:
        return None if r.trajectory is None else r.trajectory.rmse_m

    for r in results[1:]:
        g = _pct(r.gaussians, base.gaussians)
        m = _pct(r.memory.headline_bytes, base.memory.headline_bytes)
        lines.append(f"| {ABLATION_LABELS.get(r.variant, r.variant)} | {_fmt(g, '+.1f')} % | {_fmt(m, '+.1f')} % "
                     f"| {diff(r.frames_quality.psnr_db, base.frames_quality.psnr_db)} "
                     f"| {diff(r.keyframes_quality.psnr_db, base.keyframes_quality.psnr_db)} "
                     f"| {diff(ate(r), ate(base), 100.0)} |")
    return "\n".join(lines) + "\n"


def ablation_json(res: AblationResult) -> dict[str, object]:
    """``ablation.json``: every variant's results plus the side-by-side table."""
    return {**res.as_dict(), "table": ablation_table(res.results)}
