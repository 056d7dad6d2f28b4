"""Image pairs for unordered frames beyond the exhaustive matcher's reach: retrieval by visual words.

Exhaustive matching costs one SIFT match per pair of images, quadratic in the frames (86 panoramas of
six faces: 131 k face pairs, 5.4 min on 2 cores); the sequential matcher only pairs neighbours in file
order, which a folder of photos or panoramas does not have. Retrieval pairs each frame with the
``neighbours`` frames most alike in their SIFT words instead (the idea of COLMAP's vocabulary-tree
matcher, whose trained tree cannot be downloaded here): a vocabulary is clustered from the capture's
own descriptors (k-means, seeded), every frame becomes a TF-IDF histogram of its words (a panorama's
six faces pooled), and frames are compared by cosine similarity.

Pure numpy functions, no state.
"""

from __future__ import annotations

import numpy as np

__all__ = ["content_sample", "kmeans", "assign_words", "tfidf", "retrieval_pairs"]


def _sq_distances(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    return (x * x).sum(1)[:, None] - 2.0 * x @ centres.T + (centres * centres).sum(1)[None, :]


def assign_words(descriptors: np.ndarray, centres: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Index of the nearest centre (Euclidean) of each descriptor (N, D) -> (N,) int64."""
    x = np.asarray(descriptors, dtype=np.float32)
    c = np.asarray(centres, dtype=np.float32)
    out = np.empty(len(x), dtype=np.int64)
    for s in range(0, len(x), chunk):
        out[s : s + chunk] = np.argmin(_sq_distances(x[s : s + chunk], c), axis=1)
    return out


_HASH_PRIME = 2**31 - 1


def content_sample(chunks: list[np.ndarray], size: int, seed: int = 0) -> np.ndarray:
    """Up to ``size`` rows of the row-stacked ``chunks`` (each (N_i, D)) as float32, chosen by their
    content, not their position: the rows with the smallest seeded universal hash
    ``(row . w) mod p`` of their integer values (float rows are quantised to 1/1024 first), so a
    uniform sample, in the same order, whatever order the rows come in.

    A vocabulary sampled by position changed with the order in which SIFT's threads wrote a frame's
    features, and with it the retrieval pairs (81-92 pairs for one 24-frame folder, 2026-11-27).
    Rows are hashed chunk by chunk, so an 86-panorama pool (4 M uint8 descriptors) is never copied
    as float32. Exact duplicate rows tie and keep their stacking order.
    """
    chunks = [np.asarray(c) for c in chunks if len(c)]
    if not chunks:
        return np.zeros((0, 0), dtype=np.float32)
    weights = np.random.default_rng(seed).integers(1, _HASH_PRIME, size=chunks[0].shape[1], dtype=np.int64)

    def integers(c: np.ndarray) -> np.ndarray:
        return c.astype(np.int64) if c.dtype.kind in "iub" else np.round(c * 1024.0).astype(np.int64)

    # uint8 x 2^31 x 128 dimensions < 2^46: no overflow for SIFT; reduce per column otherwise.
    keys = np.concatenate(
        [((integers(c) % _HASH_PRIME) * weights % _HASH_PRIME).sum(1) % _HASH_PRIME for c in chunks]
    )
    chosen = np.argsort(keys, kind="stable")[: int(size)]  # in hash order, so k-means' start is too
    offsets = np.cumsum([0] + [len(c) for c in chunks])
    which = np.searchsorted(offsets, chosen, side="right") - 1
    out = np.empty((len(chosen), chunks[0].shape[1]), dtype=np.float32)
    for k, c in enumerate(chunks):
        rank = np.flatnonzero(which == k)
        out[rank] = c[chosen[rank] - offsets[k]]
    return out


def kmeans(x: np.ndarray, k: int, iterations: int = 10, seed: int = 0) -> np.ndarray:
    """(k', D) centres of ``x`` (N, D) by Lloyd's iterations from k distinct samples, k' = min(k, N); an
    emptied cluster is re-seeded with the sample farthest from its centre."""
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 2 or len(x) == 0:
        raise ValueError(f"kmeans needs a non-empty (N, D) array, got shape {x.shape}")
    rng = np.random.default_rng(seed)
    k = min(int(k), len(x))
    centres = x[rng.choice(len(x), size=k, replace=False)].copy()
    for _ in range(iterations):
        d = _sq_distances(x, centres)
        label = np.argmin(d, axis=1)
        counts = np.bincount(label, minlength=k)
        sums = np.zeros_like(centres)
        np.add.at(sums, label, x)
        full = counts > 0
        centres[full] = sums[full] / counts[full, None]
        if not full.all():
            far = np.argsort(-d[np.arange(len(x)), label])[: int((~full).sum())]
            centres[~full] = x[far]
    return centres


def tfidf(words: list[np.ndarray], vocabulary: int) -> np.ndarray:
    """(F, V) L2-normalised TF-IDF histograms of each frame's word ids (a frame with no word: zeros)."""
    hist = np.stack([np.bincount(np.asarray(w, dtype=np.int64), minlength=vocabulary) for w in words]).astype(
        np.float64
    )
    df = (hist > 0).sum(0)
    idf = np.log(len(words) / np.maximum(df, 1))
    tf = hist / np.maximum(hist.sum(1, keepdims=True), 1.0)
    v = tf * idf
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(norm > 0, v / np.where(norm > 0, norm, 1.0), 0.0)


def retrieval_pairs(vectors: np.ndarray, neighbours: int) -> list[tuple[int, int]]:
    """Sorted unique frame pairs (i < j): each frame with its ``neighbours`` most similar others
    (cosine similarity of ``vectors`` (F, V); ties broken by index), so every frame is in a pair."""
    v = np.asarray(vectors, dtype=np.float64)
    n = len(v)
    if neighbours < 1:
        raise ValueError(f"retrieval neighbours must be >= 1, got {neighbours}")
    sim = v @ v.T
    np.fill_diagonal(sim, -np.inf)
    k = min(int(neighbours), n - 1)
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        order = np.lexsort((np.arange(n), -sim[i]))[:k]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in order)
    return sorted(pairs)
