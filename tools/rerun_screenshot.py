"""Screenshot of the Rerun web viewer showing a saved recording, taken in headless Chromium.

    python tools/rerun_screenshot.py run.rrd                      # -> benchmarks/figures/rerun_view.png
    python tools/rerun_screenshot.py run.rrd --matplotlib         # the same content drawn by matplotlib

The recording is served by ``rerun --serve-web`` (web viewer over HTTP, the data over gRPC) and
opened in Debian's ``chromium`` (``apt-get install chromium``) with a software GPU (SwiftShader),
so no display or GPU is needed. ``--matplotlib`` instead draws what the recording holds (the last
map seen from above, trajectory, keyframes, the last frame/render pair, PSNR and map size over the
run) to ``rerun_view_matplotlib.png``: a stand-in where the web viewer cannot render.
"""
from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

FIGURES = Path(__file__).resolve().parents[1] / "benchmarks" / "figures"
# SwiftShader: Chromium's CPU implementation of WebGL/Vulkan. The web viewer asks for WebGPU first
# and falls back to WebGL2; ``renderer=webgl`` skips the attempt.
GPU_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             "--enable-webgl", "--use-gl=angle"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_http(url: str, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            if time.monotonic() > end:
                raise SystemExit(f"the web viewer did not come up at {url} within {timeout_s:.0f} s")
            time.sleep(0.5)


def _drawn(png: Path) -> bool:
    """False for the loading screen: one dark colour over nearly the whole image."""
    import cv2
    import numpy as np

    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    if img is None:
        return False
    values, counts = np.unique(img, return_counts=True)
    return counts.max() / img.size < 0.8


def web_screenshot(rrd: Path, out: Path, size: tuple[int, int], wait_s: float, chromium: str) -> Path:
    """Serve ``rrd`` with ``rerun --serve-web`` and screenshot the web viewer with headless Chromium."""
    browser = shutil.which(chromium)
    if browser is None:
        raise SystemExit(f"no {chromium} on PATH (Debian: apt-get install -y chromium)")
    web_port, grpc_port = _free_port(), _free_port()
    server = subprocess.Popen(["rerun", "--serve-web", "--web-viewer-port", str(web_port), "--port", str(grpc_port),
                               str(rrd)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        _wait_http(f"http://127.0.0.1:{web_port}/", 60.0)
        data = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
        url = f"http://127.0.0.1:{web_port}/?url={data}&renderer=webgl"
        out.parent.mkdir(parents=True, exist_ok=True)
        # --virtual-time-budget is no promise that the Wasm app has loaded and drawn (its compile
        # runs in real time): a shot of the loading screen is retried with twice the budget.
        for attempt in range(3):
            budget_s = wait_s * 2**attempt
            with tempfile.TemporaryDirectory() as profile:
                cmd = [browser, "--headless=new", "--no-sandbox", "--hide-scrollbars", f"--user-data-dir={profile}",
                       *GPU_FLAGS, f"--window-size={size[0]},{size[1]}", f"--virtual-time-budget={int(budget_s * 1000)}",
                       f"--screenshot={out}", url]
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=budget_s + 180)
            if proc.returncode != 0 or not out.exists():
                raise SystemExit(f"chromium failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
            if _drawn(out):
                return out
            print(f"attempt {attempt + 1}: the viewer had not drawn yet after {budget_s:.0f} s of virtual time")
        raise SystemExit(f"the web viewer did not draw within {budget_s:.0f} s (see {out})")
    finally:
        server.terminate()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()


def matplotlib_figure(rrd: Path, out: Path) -> Path:
    """Draw the recording's content with matplotlib (no viewer): see the module docstring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import pyarrow as pa
    from rerun.chunk import RrdReader

    from memgs_ros.core.runtime.atomic import atomic_write

    rows: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(rrd)).stream():
        batch = chunk.to_record_batch()
        cols = {n: (c.cast(pa.int64()) if pa.types.is_timestamp(c.type) else c).to_pylist()
                for n, c in zip(batch.schema.names, batch.columns)}
        for i in range(batch.num_rows):
            rows.setdefault(chunk.entity_path, []).append({n: v[i] for n, v in cols.items()})
    for r in rows.values():
        r.sort(key=lambda x: (x.get("frame") or -1, x["rerun.controls.RowId"]))

    def last(entity: str, comp: str):  # noqa: ANN202
        vals = [r[comp] for r in rows.get(entity, []) if r.get(comp) is not None]
        return vals[-1] if vals else None

    def series(entity: str) -> tuple[list[int], list[float]]:
        pts = [(r.get("frame") or 0, r["Scalars:scalars"][0]) for r in rows.get(entity, []) if r.get("Scalars:scalars")]
        return [p[0] for p in pts], [p[1] for p in pts]

    fig = plt.figure(figsize=(16, 9), dpi=100)
    grid = fig.add_gridspec(3, 4)
    ax = fig.add_subplot(grid[:, :2])
    centers = last("/world/map", "GaussianSplats3D:centers")
    if centers is not None:
        xyz = np.asarray(centers)
        packed = np.asarray(last("/world/map", "GaussianSplats3D:colors"), dtype=np.uint32)
        rgba = np.stack([(packed >> s) & 255 for s in (24, 16, 8, 0)], axis=1) / 255.0
        order = np.argsort(-xyz[:, 1])  # world y points down: draw the lowest first, the top last
        ax.scatter(xyz[order, 0], xyz[order, 2], c=rgba[order], s=1.0, linewidths=0)
        lo, hi = np.percentile(xyz[:, [0, 2]], [1, 99], axis=0)  # a few stray Gaussians would zoom out
        pad = 0.1 * (hi - lo)
        ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        ax.set_title(f"map from above: {len(xyz)} Gaussians (last map logged)")
    strips = last("/world/trajectory", "LineStrips3D:strips")
    if strips:
        t = np.asarray(strips[0])
        ax.plot(t[:, 0], t[:, 2], color="orange", lw=1.5, label="trajectory")
    kf = [last(e, "Transform3D:translation") for e in rows if e.startswith("/world/keyframes/")]
    kf = np.asarray([k[0] for k in kf if k])
    if len(kf):
        ax.scatter(kf[:, 0], kf[:, 2], marker="^", color="red", s=20, label="keyframes")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_aspect("equal")
    ax.legend(loc="upper right")
    for col, (entity, title) in enumerate((("/views/frame", "frame"), ("/views/render", "render"))):
        a = fig.add_subplot(grid[0, 2 + col])
        blob = last(entity, "EncodedImage:blob")
        if blob is not None:
            import cv2

            img = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
            a.imshow(img)
        a.set_title(f"last {title}")
        a.axis("off")
    a = fig.add_subplot(grid[1, 2:])
    a.plot(*series("/quality/psnr_db"), ".-")
    a.set_ylabel("PSNR (dB)")
    a = fig.add_subplot(grid[2, 2:])
    a.plot(*series("/stats/gaussians/mapper"), label="mapper")
    a.plot(*series("/stats/gaussians/merger"), label="merger")
    a.set_ylabel("Gaussians")
    a.set_xlabel("frame")
    a.legend()
    fig.suptitle(f"{rrd.name}: the Rerun recording's content drawn by matplotlib (not a Rerun screenshot)")
    fig.tight_layout()
    atomic_write(out, lambda f: fig.savefig(f, format="png"))
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("rrd", type=Path, help="a recording (memgs run --rerun-save, memgs view --save)")
    p.add_argument("--out", type=Path, default=None,
                   help="PNG path (default: benchmarks/figures/rerun_view.png, or rerun_view_matplotlib.png)")
    p.add_argument("--size", default="1600x900", help="window size WxH")
    p.add_argument("--wait-s", type=float, default=40.0, help="time the page gets to load and draw")
    p.add_argument("--chromium", default="chromium", help="browser executable")
    p.add_argument("--matplotlib", action="store_true", help="draw the content with matplotlib instead")
    args = p.parse_args(argv)
    if not args.rrd.is_file():
        raise SystemExit(f"{args.rrd}: no such recording")
    if args.matplotlib:
        out = matplotlib_figure(args.rrd, args.out or FIGURES / "rerun_view_matplotlib.png")
    else:
        w, h = (int(v) for v in args.size.lower().split("x"))
        out = web_screenshot(args.rrd, args.out or FIGURES / "rerun_view.png", (w, h), args.wait_s, args.chromium)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
