"""Build the ORB vocabulary the package ships (memgs_ros/data/orb_vocabulary.npz) from synthetic
room renders: the tracker's ORB descriptors of both camera paths at two sizes, clustered into a
vocabulary tree (memgs_ros.core.tracking.features.vocabulary.build_vocabulary).

    python tools/build_vocabulary.py --out memgs_ros/data/orb_vocabulary.npz
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from memgs_ros.core.tracking.features.vocabulary import VOCABULARY_RESOURCE, build_vocabulary


def _training_descriptors(seeds: Sequence[int], views_per_seed: int) -> list[np.ndarray]:
    """ORB descriptors (tracker defaults) of synthetic room renders, both camera paths, two sizes."""
    import cv2

    from memgs_ros.core.tracking.config import TrackerConfig
    from memgs_ros.core.tracking.features.features import OrbExtractor
    from memgs_ros.io.synthetic import SyntheticSpec, build_scene, render, trajectory

    out = []
    extractor = OrbExtractor(TrackerConfig())
    for seed in seeds:
        scene = build_scene(seed)
        for path, (w, h) in (("wobble", (640, 480)), ("loop", (640, 480)), ("loop", (320, 240))):
            spec = SyntheticSpec(width=w, height=h, n_frames=views_per_seed, seed=seed, path=path, supersample=1)
            _, poses = trajectory(spec)
            for T_wc in poses:
                rgb, _ = render(scene, spec.camera, T_wc, 1)
                gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
                out.append(extractor.extract(gray, spec.camera, None).desc)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Build the ORB vocabulary from synthetic room renders.")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "memgs_ros" / "data" / VOCABULARY_RESOURCE))
    ap.add_argument("--seeds", default="1,2,3,4,5,6,7,8")
    ap.add_argument("--views", type=int, default=8, help="views per seed and path")
    ap.add_argument("--branching", type=int, default=12)
    ap.add_argument("--depth", type=int, default=3)
    args = ap.parse_args(argv)
    desc = _training_descriptors([int(s) for s in args.seeds.split(",")], args.views)
    vocab = build_vocabulary(desc, args.branching, args.depth)
    vocab.save(args.out)
    used = int((vocab.idf > 0).sum())
    print(f"{args.out}: {vocab.n_words} words ({used} seen) from {len(desc)} images, "
          f"{sum(len(d) for d in desc)} descriptors, {Path(args.out).stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
