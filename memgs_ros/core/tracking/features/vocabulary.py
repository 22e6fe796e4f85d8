"""Bag of binary words: an ORB vocabulary tree, TF-IDF vectors and a keyframe database.

The vocabulary is a tree of ``branching ** depth`` words built by hierarchical k-majority
clustering of 256-bit ORB descriptors (k-means with Hamming distance; a centre is the bitwise
majority of its members), the idea of DBoW2. A descriptor descends the tree, at each level to
the nearest of ``branching`` children, so transforming M descriptors costs M * branching * depth
Hamming distances. Word weights are TF-IDF with the IDF learnt from the training images; vectors
are L1-normalised and compared with DBoW2's L1 score ``1 - |a - b|_1 / 2`` (1 = identical).

The shipped vocabulary (``memgs_ros/data/orb_vocabulary.npz``, ~70 KB) was built from renders
of the synthetic room (seeds 1-8, not the tests' and benchmarks' seed 0) by::

    python tools/build_vocabulary.py --out memgs_ros/data/orb_vocabulary.npz

``KeyframeDatabase`` is the inverted index (word -> keyframes containing it) that answers
"which keyframes look like this one" in time proportional to the shared words, not to the
number of keyframes.
"""
from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from memgs_ros.core.tracking.features.features import DESCRIPTOR_BYTES
from memgs_ros.core.tracking.kernel_calls import numba_available, words_kernel
from memgs_ros.errors import DataError

VOCABULARY_RESOURCE = "orb_vocabulary.npz"  # in the memgs_ros.data package


def _signs(desc: np.ndarray) -> np.ndarray:
    """Packed descriptors [M, 32] uint8 -> [M, 256] float32 of +-1 (Hamming = (256 - a.b) / 2)."""
    return np.unpackbits(np.ascontiguousarray(desc, dtype=np.uint8), axis=1).astype(np.float32) * 2.0 - 1.0


def _hamming_matrix(a_signs: np.ndarray, b_signs: np.ndarray) -> np.ndarray:
    """[M, 256] x [K, 256] +-1 arrays -> [M, K] Hamming distances (float32)."""
    return (256.0 - a_signs @ b_signs.T) * 0.5


@dataclass(frozen=True, eq=False)
class BowVector:
    """A sparse TF-IDF vector: words [W] int64 sorted, weights [W] float64 summing to 1."""

    words: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.words)


def bow_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 score of two L1-normalised vectors, in [0, 1] (1 = same words, same weights)."""
    common, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    if len(common) == 0:
        return 0.0
    wa, wb = a.weights[ia], b.weights[ib]
    return float(0.5 * np.sum(wa + wb - np.abs(wa - wb)))


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A vocabulary tree.

    levels: ``depth`` arrays of packed centres, level l is [branching ** (l + 1), 32] uint8; the
      children of node i of level l are nodes i * branching .. (i + 1) * branching - 1 of level l + 1.
    idf: [branching ** depth] float64 inverse document frequency of each word (leaf).
    """

    branching: int
    depth: int
    levels: tuple[np.ndarray, ...]
    idf: np.ndarray

    def __post_init__(self) -> None:
        if len(self.levels) != self.depth:
            raise DataError(f"vocabulary: {len(self.levels)} levels for depth {self.depth}")
        for lvl, c in enumerate(self.levels):
            if c.shape != (self.branching ** (lvl + 1), DESCRIPTOR_BYTES) or c.dtype != np.uint8:
                raise DataError(f"vocabulary level {lvl}: centres {c.shape} {c.dtype}, expected "
                                f"({self.branching ** (lvl + 1)}, {DESCRIPTOR_BYTES}) uint8")
        if self.idf.shape != (self.n_words,):
            raise DataError(f"vocabulary: idf {self.idf.shape}, expected ({self.n_words},)")
        object.__setattr__(self, "_level_signs", tuple(_signs(c) for c in self.levels))
        object.__setattr__(self, "_packed_centres", np.concatenate(self.levels))

    @property
    def n_words(self) -> int:
        return self.branching ** self.depth

    def words(self, desc: np.ndarray) -> np.ndarray:
        """Word id [M] int64 of each packed descriptor [M, 32] (descend the tree greedily): the
        compiled kernel (popcounts of the packed bits, the GIL released) where numba is at hand."""
        if not numba_available():
            return self._words_reference(desc)
        return words_kernel(desc, self._packed_centres, self.branching, self.depth)  # type: ignore[attr-defined]

    def _words_reference(self, desc: np.ndarray) -> np.ndarray:
        """Twin of ``kernel_calls.words_kernel`` (numpy: +-1 dot products, the largest the nearest)."""
        m = len(desc)
        if m == 0:
            return np.zeros(0, np.int64)
        x = _signs(desc)  # [M, 256]
        node = np.zeros(m, np.int64)
        k = self.branching
        signs: tuple[np.ndarray, ...] = self._level_signs  # type: ignore[attr-defined]
        for lvl in range(self.depth):
            children = node[:, None] * k + np.arange(k)[None, :] if lvl else np.tile(np.arange(k), (m, 1))  # [M, k]
            c = signs[lvl][children]  # [M, k, 256]
            dots = np.einsum("mkb,mb->mk", c, x)  # largest dot = smallest Hamming
            node = children[np.arange(m), np.argmax(dots, axis=1)]
        return node

    def transform(self, desc: np.ndarray) -> BowVector:
        """TF-IDF vector of one image's descriptors [M, 32] (L1-normalised)."""
        w = self.words(desc)
        if len(w) == 0:
            return BowVector(np.zeros(0, np.int64), np.zeros(0))
        words, counts = np.unique(w, return_counts=True)
        weights = counts / len(w) * self.idf[words]
        total = weights.sum()
        keep = weights > 0
        words, weights = words[keep], weights[keep]
        return BowVector(words, weights / total if total > 0 else weights)

    def save(self, path: str | Path) -> None:
        np.savez_compressed(path, branching=self.branching, depth=self.depth, idf=self.idf.astype(np.float32),
                            **{f"level{i}": c for i, c in enumerate(self.levels)})  # type: ignore[arg-type]

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        try:
            with np.load(path, allow_pickle=False) as z:
                depth = int(z["depth"])
                return cls(int(z["branching"]), depth, tuple(z[f"level{i}"] for i in range(depth)),
                           z["idf"].astype(np.float64))
        except (OSError, KeyError, ValueError) as err:
            raise DataError(f"Could not read the ORB vocabulary at {path}: {err}") from err


@functools.lru_cache(maxsize=1)
def default_vocabulary() -> Vocabulary:
    """The vocabulary shipped with the package (loaded once)."""
    ref = resources.files("memgs_ros.data").joinpath(VOCABULARY_RESOURCE)
    with resources.as_file(ref) as path:
        return Vocabulary.load(path)


# ------------------------------------------------------------------------------ building


def _k_majority(signs: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Cluster +-1 descriptors [N, 256] into k centres [k, 256] (+-1) with Hamming k-means++ seeding
    and majority-vote updates; returns (centres, assignment [N]). With fewer than k distinct
    descriptors some centres repeat (their words stay empty)."""
    n = len(signs)
    if n == 0:
        return np.ones((k, signs.shape[1]), np.float32), np.zeros(0, np.int64)
    centres = [signs[rng.integers(n)]]
    d_min = _hamming_matrix(signs, centres[0][None])[:, 0]
    for _ in range(1, k):
        p = d_min ** 2
        total = p.sum()
        j = int(rng.choice(n, p=p / total)) if total > 0 else int(rng.integers(n))
        centres.append(signs[j])
        d_min = np.minimum(d_min, _hamming_matrix(signs, signs[j][None])[:, 0])
    c = np.stack(centres)
    assign = np.zeros(n, np.int64)
    for it in range(iterations):
        new_assign = np.argmin(_hamming_matrix(signs, c), axis=1)
        if it and np.array_equal(new_assign, assign):
            break
        assign = new_assign
        for j in range(k):
            members = signs[assign == j]
            if len(members):
                c[j] = np.where(members.sum(axis=0) >= 0, 1.0, -1.0)
    return c, assign


def build_vocabulary(images_desc: Sequence[np.ndarray], branching: int = 12, depth: int = 3,
                     seed: int = 0, iterations: int = 10) -> Vocabulary:
    """Hierarchical k-majority over the descriptors of training images (each [M_i, 32] uint8);
    the IDF of a word is log(images / images containing it) (0 for words no image has)."""
    rng = np.random.default_rng(seed)
    all_desc = np.concatenate([d for d in images_desc if len(d)])
    signs = _signs(all_desc)
    level_centres: list[np.ndarray] = []
    groups = [np.arange(len(signs))]  # members of each node of the current level
    for _ in range(depth):
        centres = np.empty((len(groups) * branching, signs.shape[1]), np.float32)
        next_groups: list[np.ndarray] = []
        for g, members in enumerate(groups):
            c, assign = _k_majority(signs[members], branching, rng, iterations)
            centres[g * branching:(g + 1) * branching] = c
            next_groups.extend(members[assign == j] for j in range(branching))
        level_centres.append(np.packbits(centres > 0, axis=1))
        groups = next_groups
    vocab = Vocabulary(branching, depth, tuple(level_centres), np.zeros(branching ** depth))
    n_docs = np.zeros(vocab.n_words)
    for d in images_desc:
        n_docs[np.unique(vocab.words(d))] += 1
    idf = np.where(n_docs > 0, np.log(len(images_desc) / np.maximum(n_docs, 1)), 0.0)
    return Vocabulary(branching, depth, vocab.levels, idf)


# ------------------------------------------------------------------------------ database


class KeyframeDatabase:
    """Inverted index of keyframe BoW vectors: word -> {keyframe id: weight}.

    One owner each: the tracker's back-end (loop search) and front-end (relocalisation) keep one apiece.
    """

    def __init__(self) -> None:
        self._index: dict[int, dict[int, float]] = {}
        self._vectors: dict[int, BowVector] = {}

    def __len__(self) -> int:
        return len(self._vectors)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._vectors

    def vector(self, kf_id: int) -> BowVector | None:
        return self._vectors.get(kf_id)

    def add(self, kf_id: int, bow: BowVector) -> None:
        self.remove(kf_id)
        self._vectors[kf_id] = bow
        for w, x in zip(bow.words.tolist(), bow.weights.tolist()):
            self._index.setdefault(w, {})[kf_id] = x

    def remove(self, kf_id: int) -> None:
        bow = self._vectors.pop(kf_id, None)
        if bow is None:
            return
        for w in bow.words.tolist():
            posting = self._index.get(w)
            if posting is not None:
                posting.pop(kf_id, None)
                if not posting:
                    del self._index[w]

    def query(self, bow: BowVector, exclude: Iterable[int] = (), min_score: float = 0.0,
              max_results: int = 0) -> list[tuple[int, float]]:
        """Keyframes sharing words with ``bow``, as (id, L1 score) best first; ``exclude`` ids
        skipped, scores below ``min_score`` dropped, at most ``max_results`` (0 = all)."""
        skip = set(exclude)
        acc: dict[int, float] = {}
        for w, x in zip(bow.words.tolist(), bow.weights.tolist()):
            for kf_id, y in self._index.get(w, {}).items():
                if kf_id not in skip:
                    # |x| + |y| - |x - y| = 2 min(x, y) for the positive weights of a shared word
                    acc[kf_id] = acc.get(kf_id, 0.0) + min(x, y)
        out = sorted(((k, s) for k, s in acc.items() if s >= min_score), key=lambda kv: -kv[1])
        return out[:max_results] if max_results > 0 else out


__all__ = ["BowVector", "KeyframeDatabase", "Vocabulary", "bow_score", "build_vocabulary", "default_vocabulary"]
