"""SSIM (fast grouped-separable path vs references), PSNR and frame matching."""
from __future__ import annotations

import sys
from collections.abc import Iterator

import numpy as np
import pytest
import torch
from scipy import ndimage

from memgs_ros.core.metrics import ssim as ssim_module
from memgs_ros.core.metrics.image import (
    FrameScore,
    make_lpips,
    match_frames,
    psnr,
    score_frame,
    ssim_value,
    summarize_scores,
)
from memgs_ros.core.metrics.ssim import _ssim_map, gaussian_window_1d, ssim, ssim_map
from memgs_ros.core.runtime.cpu import numba_available
from memgs_ros.errors import ConfigError


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    """On a loaded shared machine each tiny OpenMP-parallel conv waits for a scheduler tick:
    measured 365 ms vs 1.2 ms per small SSIM forward with 2 threads vs 1 at load 11. The
    gradient checks run hundreds of them, so these tests use one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _numpy_ssim_map(a: np.ndarray, b: np.ndarray, size: int = 11, sigma: float = 1.5,
                    c1: float = 1e-4, c2: float = 9e-4) -> np.ndarray:
    """Textbook SSIM: explicit 2-D Gaussian window, zero padding, float64. a, b: [C, H, W]."""
    x = np.arange(size) - (size - 1) / 2
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    w = np.outer(g, g)
    w /= w.sum()

    def f(img: np.ndarray) -> np.ndarray:
        return np.stack([ndimage.correlate(ch, w, mode="constant", cval=0.0) for ch in img])

    mu1, mu2 = f(a), f(b)
    s11 = f(a * a) - mu1 ** 2
    s22 = f(b * b) - mu2 ** 2
    s12 = f(a * b) - mu1 * mu2
    return ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))


def _require_numba() -> None:
    pytest.importorskip("numba")
    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")


@pytest.fixture(params=["numba", "torch"])
def fast_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a test once per fast path of ssim_map on CPU: the numba kernels and the grouped torch
    convolution (what CUDA and installs without numba use)."""
    if request.param == "numba":
        _require_numba()
    else:
        monkeypatch.setattr(ssim_module, "_use_numba", lambda a: False)
    return str(request.param)


def _assert_path(out: torch.Tensor, path: str) -> None:
    """The map came from the expected autograd Function (so a test cannot pass on the other path)."""
    fn = out.grad_fn
    while fn is not None and type(fn).__name__.startswith("Squeeze"):  # unbatched input
        fn = fn.next_functions[0][0]
    name = type(fn).__name__
    assert "SsimMap" in name and ("Numba" in name) == (path == "numba"), name


def _pair(shape: tuple[int, ...], seed: int = 0, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=g, dtype=dtype)
    # b is half image, half noise so SSIM lands well inside (0, 1).
    b = (0.5 * a + 0.5 * torch.rand(shape, generator=g, dtype=dtype)).clamp(0, 1)
    return a, b


def test_window_is_normalised_and_symmetric() -> None:
    k = gaussian_window_1d(11, 1.5, torch.float64, torch.device("cpu"))
    assert k.shape == (11,)
    assert torch.isclose(k.sum(), torch.tensor(1.0, dtype=torch.float64))
    assert torch.equal(k, k.flip(0))
    assert int(k.argmax()) == 5
    with pytest.raises(ValueError, match="odd"):
        gaussian_window_1d(10, 1.5, torch.float32, torch.device("cpu"))


def test_identical_images_give_one() -> None:
    a, _ = _pair((3, 37, 53))
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)
    m = ssim_map(a, a)
    assert m.shape == a.shape
    assert torch.allclose(m, torch.ones_like(m), atol=1e-5)


@pytest.mark.parametrize("shape", [(3, 40, 56), (2, 3, 31, 47), (1, 1, 12, 12), (3, 5, 64)])
def test_fast_path_matches_2d_window_twin(shape: tuple[int, ...], fast_path: str) -> None:
    a, b = _pair(shape, seed=1)
    fast = ssim_map(a, b)
    ref = _ssim_map(a, b)
    assert fast.shape == a.shape
    assert torch.allclose(fast, ref, atol=1e-5), float((fast - ref).abs().max())


def test_matches_textbook_numpy_ssim(fast_path: str) -> None:
    a, b = _pair((3, 33, 41), seed=2, dtype=torch.float64)
    ref = _numpy_ssim_map(a.numpy(), b.numpy())
    fast = ssim_map(a, b).numpy()
    assert np.abs(fast - ref).max() < 1e-5
    assert ssim(a, b).item() == pytest.approx(ref.mean(), abs=1e-6)
    # The pair is dissimilar enough that this comparison means something.
    assert 0.2 < ref.mean() < 0.95


def test_other_window_and_float32_against_numpy(fast_path: str) -> None:
    a, b = _pair((3, 30, 30), seed=3)
    ref = _numpy_ssim_map(a.double().numpy(), b.double().numpy(), size=7, sigma=1.0)
    fast = ssim_map(a, b, window_size=7, sigma=1.0).double().numpy()
    assert np.abs(fast - ref).max() < 1e-5


def test_gradcheck_double(fast_path: str) -> None:
    # Small image and a 5x5 window so the window still overlaps the zero padding on every side;
    # fast mode checks random projections of the Jacobian (the full one is covered by the
    # comparison with the 2-D twin below).
    a, b = _pair((1, 2, 7, 8), seed=4, dtype=torch.float64)
    a.requires_grad_(True)
    b.requires_grad_(True)
    _assert_path(ssim_map(a, b), fast_path)
    assert torch.autograd.gradcheck(lambda x, y: ssim_map(x, y, window_size=5, sigma=1.0), (a, b),
                                    eps=1e-6, atol=1e-5, fast_mode=True)
    assert torch.autograd.gradcheck(lambda x, y: ssim(x, y), (a, b), eps=1e-6, atol=1e-5)


def test_gradient_matches_twin_with_random_cotangent(fast_path: str) -> None:
    a, b = _pair((2, 3, 20, 24), seed=5, dtype=torch.float64)
    a.requires_grad_(True)
    b.requires_grad_(True)
    v = torch.randn(2, 3, 20, 24, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    out = ssim_map(a, b)
    _assert_path(out, fast_path)
    v_fast = torch.autograd.grad(out, (a, b), v)
    v_ref = torch.autograd.grad(_ssim_map(a, b), (a, b), v)
    for g_fast, g_ref in zip(v_fast, v_ref):
        assert torch.allclose(g_fast, g_ref, atol=1e-10)
        assert g_fast.abs().max() > 0


@pytest.mark.parametrize("which", ["first", "second"])
def test_gradient_when_only_one_image_needs_it(which: str, fast_path: str) -> None:
    a, b = _pair((3, 17, 21), seed=10, dtype=torch.float64)
    x = a if which == "first" else b
    x.requires_grad_(True)
    v = torch.randn(3, 17, 21, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    out = ssim_map(a, b)
    _assert_path(out, fast_path)
    (g_fast,) = torch.autograd.grad(out, (x,), v)
    (g_ref,) = torch.autograd.grad(_ssim_map(a, b), (x,), v)
    assert torch.allclose(g_fast, g_ref, atol=1e-10) and g_fast.abs().max() > 0


# Odd sizes, sizes below the window (every window overlaps the zero padding), batched and not.
NUMBA_SHAPES = [(3, 240, 320), (3, 5, 4), (1, 1, 1, 1), (2, 3, 7, 13), (1, 2, 12, 11), (3, 33, 64), (1, 9)]


@pytest.mark.parametrize("shape", NUMBA_SHAPES[:-1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_path_matches_twin_forward_and_backward(shape: tuple[int, ...], dtype: torch.dtype) -> None:
    """The compiled path against the 2-D twin evaluated in float64, both images needing
    gradients, random cotangent. float32 tolerances: map 1e-5 absolute (the twin's own float32
    error is ~8e-6 at 320x240), gradient 1e-5 of its largest entry (measured ~1e-6)."""
    _require_numba()
    a, b = _pair(shape, seed=20)
    a, b = a.to(dtype).requires_grad_(True), b.to(dtype).requires_grad_(True)
    v = torch.randn(shape, generator=torch.Generator().manual_seed(21), dtype=dtype)
    out = ssim_map(a, b)
    _assert_path(out, "numba")
    assert out.dtype == dtype and out.shape == a.shape
    a64, b64 = a.detach().double().requires_grad_(True), b.detach().double().requires_grad_(True)
    ref = _ssim_map(a64, b64)
    v_ref = torch.autograd.grad(ref, (a64, b64), v.double())
    v_out = torch.autograd.grad(out, (a, b), v)
    f32 = dtype == torch.float32
    assert float((out.detach().double() - ref.detach()).abs().max()) < (1e-5 if f32 else 1e-12)
    for g_out, g_ref in zip(v_out, v_ref):
        scale = float(g_ref.abs().max())
        assert scale > 0 and g_out.dtype == dtype
        assert float((g_out.double() - g_ref).abs().max()) <= (1e-5 if f32 else 1e-12) * scale


@pytest.mark.parametrize(("window", "sigma"), [(1, 1.0), (3, 0.3), (7, 1.0), (11, 1.5), (15, 3.0)])
def test_numba_path_other_windows(window: int, sigma: float) -> None:
    """Other windows, one whose outer taps underflow to 0 (3, 0.3 -> 4e-25 relative), and a
    window wider than the image (15 > 9)."""
    _require_numba()
    a, b = _pair((2, 9, 10), seed=22, dtype=torch.float64)
    a.requires_grad_(True)
    v = torch.randn(2, 9, 10, generator=torch.Generator().manual_seed(23), dtype=torch.float64)
    out = ssim_map(a, b, window_size=window, sigma=sigma)
    _assert_path(out, "numba")
    ref = _ssim_map(a, b, window_size=window, sigma=sigma)
    assert float((out.detach() - ref.detach()).abs().max()) < 1e-12
    (g_out,) = torch.autograd.grad(out, (a,), v)
    (g_ref,) = torch.autograd.grad(ref, (a,), v)
    # Window 1: var = E[x^2] - mu^2 is 0 up to rounding and S is steep there (|v_a| up to ~10).
    assert float((g_out - g_ref).abs().max()) <= 1e-12 * float(g_ref.abs().max()) and g_ref.abs().max() > 0


def test_numba_path_without_gradients_and_non_contiguous_input() -> None:
    _require_numba()
    a, b = _pair((3, 40, 30), seed=24)
    with_grad = ssim_map(a.clone().requires_grad_(True), b)
    with torch.no_grad():
        plain = ssim_map(a, b)
    assert torch.equal(plain, with_grad.detach())
    # A transposed view is made contiguous first.
    t = ssim_map(a.transpose(1, 2), b.transpose(1, 2))
    assert torch.allclose(t, _ssim_map(a.transpose(1, 2).contiguous(), b.transpose(1, 2).contiguous()), atol=1e-5)


def test_numba_switch_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch) -> None:
    """MEMGS_DISABLE_NUMBA (read through runtime.numba_available) sends CPU SSIM to the torch path."""
    a, b = _pair((3, 12, 14), seed=25)
    a.requires_grad_(True)
    monkeypatch.setattr(ssim_module, "numba_available", lambda: False)
    _assert_path(ssim_map(a, b), "torch")
    assert not ssim_module._use_numba(a.to(torch.float16))
    with pytest.raises(ConfigError, match=r"numba path needs numba .* got torch.float32 on cpu \(numba available: False\)"):
        ssim_module._fast_ssim_map(a, b, 11, 1.5, 1e-4, 9e-4, 1.0, compiled=True)


def test_reductions_and_data_range() -> None:
    a, b = _pair((4, 3, 16, 18), seed=7)
    per = ssim(a, b, reduction="per_image")
    assert per.shape == (4,)
    assert torch.allclose(per.mean(), ssim(a, b), atol=1e-6)
    assert torch.allclose(ssim(a[0], b[0], reduction="per_image"), per[0], atol=1e-6)
    assert ssim(a, b, reduction="none").shape == a.shape
    # Scaling both images and the data range together leaves SSIM unchanged.
    assert ssim(a * 255, b * 255, data_range=255.0).item() == pytest.approx(ssim(a, b).item(), abs=1e-5)
    with pytest.raises(ValueError, match="reduction"):
        ssim(a, b, reduction="sum")


def test_shape_mismatch_is_refused() -> None:
    a, _ = _pair((3, 10, 10))
    with pytest.raises(AssertionError, match=r"\(3, 10, 10\) vs \(3, 10, 11\)"):
        ssim(a, torch.rand(3, 10, 11))
    with pytest.raises(AssertionError, match="floating"):
        ssim(a.to(torch.uint8), a.to(torch.uint8))


# --- PSNR, frame scores, matching ----------------------------------------------------------


def test_psnr_hand_values() -> None:
    ref = np.zeros((4, 6, 3), np.float64)
    assert psnr(np.full_like(ref, 0.1), ref) == pytest.approx(20.0, abs=1e-9)
    half = ref.copy()
    half[:2] = 0.2  # half the pixels off by 0.2: MSE 0.02
    assert psnr(half, ref) == pytest.approx(-10 * np.log10(0.02), abs=1e-9)
    # uint8 is scaled to [0, 1]: full white vs black is MSE 1, 0 dB.
    assert psnr(np.full((4, 6, 3), 255, np.uint8), np.zeros((4, 6, 3), np.uint8)) == pytest.approx(0.0)
    # Tensors are [3, H, W] and give the same number as the numpy layout.
    t = torch.from_numpy(half.transpose(2, 0, 1).copy())
    assert psnr(t, torch.zeros(3, 4, 6)) == pytest.approx(psnr(half, ref), abs=1e-9)
    assert psnr(ref, ref) == float("inf")
    with pytest.raises(AssertionError, match="differ"):
        psnr(ref, np.zeros((4, 5, 3), np.float32))


def test_ssim_value_and_score_frame() -> None:
    a, b = _pair((3, 24, 32), seed=9)
    a_np = a.numpy().transpose(1, 2, 0)
    b_np = b.numpy().transpose(1, 2, 0)
    assert ssim_value(a_np, b_np) == pytest.approx(ssim(a, b).item(), abs=1e-6)
    # The render is clamped to [0, 1] before scoring.
    over = a_np + 0.5
    s = score_frame(7, over, np.clip(over, 0, 1))
    assert s == FrameScore(stamp_ns=7, psnr_db=float("inf"), ssim=pytest.approx(1.0, abs=1e-6), lpips=None)
    s2 = score_frame(8, b_np, a_np, lpips_fn=lambda x, y: 0.25)
    assert s2.lpips == 0.25 and s2.psnr_db == pytest.approx(psnr(b_np, a_np))


def test_match_frames_within_80ms() -> None:
    gt = np.array([0, 33, 66, 100, 133]) * 1_000_000
    render = np.array([10, 70, 300]) * 1_000_000
    ir, ig = match_frames(render, gt)
    assert ir.tolist() == [0, 1] and ig.tolist() == [0, 2]
    ir, ig = match_frames(render, gt, max_dt_s=0.005)
    assert ir.tolist() == [1] and ig.tolist() == [2]


def test_summarize_scores() -> None:
    scores = [FrameScore(0, 20.0, 0.8), FrameScore(1, 30.0, 0.6), FrameScore(2, float("inf"), 1.0)]
    out = summarize_scores(scores)
    assert out["n"] == 3 and out["psnr_db"] == pytest.approx(25.0)
    assert out["ssim"] == pytest.approx(0.8) and out["lpips"] is None
    assert summarize_scores([])["n"] == 0


def test_lpips_hook_is_none_without_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "lpips", None)  # makes `import lpips` raise ImportError
    assert make_lpips() is None


def test_psnr_map_size_and_frame_strip_plots() -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from memgs_ros.evaluation.plots import frame_strip_image, plot_frame_strip, plot_map_size, plot_psnr_per_frame

    fig = Figure()
    FigureCanvasAgg(fig)
    ax1, ax2, ax3 = fig.subplots(1, 3)
    plot_psnr_per_frame(ax1, np.arange(4) * 0.1, np.array([20.0, 22.0, 24.0, 26.0]),
                        is_keyframe=np.array([True, False, True, False]))
    labels = [ln.get_label() for ln in ax1.get_lines()]
    assert labels == ["PSNR (mean 23.00 dB)", "keyframes (mean 22.00 dB)"]
    twin = plot_map_size(ax2, np.arange(3.0), np.array([1000, 2000, 1500]), np.array([1, 2, 3]) * 1024 ** 3)
    assert twin is not None and np.allclose(twin.get_lines()[0].get_ydata(), [1, 2, 3])
    assert np.allclose(ax2.get_lines()[0].get_ydata(), [1.0, 2.0, 1.5])
    render = np.full((8, 10, 3), 1.5, np.float32)  # clamped to 1
    real = np.zeros((8, 10, 3), np.uint8)
    strip = frame_strip_image([render, render], [real, real])
    assert strip.shape == (2 * 8 + 4, 2 * 10 + 4, 3)
    assert strip[:8, :10].min() == 1.0 and strip[12:, 14:].max() == 0.0 and strip[8:12].min() == 1.0
    plot_frame_strip(ax3, [render], [real], titles=["t=0.0 s"])
    assert len(ax3.get_images()) == 1 and ax3.texts[0].get_text() == "t=0.0 s"
    fig.canvas.draw()
    with pytest.raises(ValueError, match="as many renders"):
        frame_strip_image([render], [])
