"""Retrieval pairing of unordered frames (lift.pairs): k-means, word assignment, TF-IDF and the pairs."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.lift.pairs import assign_words, content_sample, kmeans, retrieval_pairs, tfidf


def test_kmeans_finds_separated_clusters_and_words_are_nearest_centres():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(6, 16)) * 20
    x = np.concatenate([c + rng.normal(size=(200, 16)) for c in truth])
    centres = kmeans(x, 6, seed=1)
    # every true centre has a found centre within the noise
    assert np.linalg.norm(truth[:, None] - centres[None], axis=2).min(1).max() < 1.0
    words = assign_words(x, centres, chunk=97)  # chunks of odd size give the same answer
    brute = np.argmin(np.linalg.norm(x[:, None] - centres[None], axis=2), axis=1)
    assert np.array_equal(words, brute)
    assert len(kmeans(x[:3], 10)) == 3  # never more centres than samples
    with pytest.raises(ValueError, match="non-empty"):
        kmeans(np.zeros((0, 4)), 2)


def test_content_sample_ignores_row_order_and_is_not_biased_towards_small_rows():
    """The vocabulary sample must not depend on the order SIFT's threads wrote features in: the same
    rows shuffled within and across chunks give the same sample, in the same order. A hash, not a
    projection: the chosen rows' mean is the pool's (a smallest-projection pick would be darkest)."""
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, size=(6000, 128), dtype=np.uint8)
    a = content_sample([pool[:1000], pool[1000:4000], pool[4000:]], 500, seed=3)
    shuffled = pool[rng.permutation(len(pool))]
    b = content_sample([shuffled[:2500], shuffled[2500:]], 500, seed=3)
    assert a.shape == (500, 128) and a.dtype == np.float32
    assert np.array_equal(a, b)
    assert abs(a.mean() - pool.mean()) < 2.0  # pool mean 127.5; per-row sd ~6.5, /sqrt(500)
    assert not np.array_equal(a, content_sample([pool], 500, seed=4))  # the seed picks the sample
    assert len(content_sample([pool[:10]], 500)) == 10  # never more than there is
    assert content_sample([np.zeros((0, 128), np.uint8)], 5).shape[0] == 0


def test_tfidf_rows_are_unit_and_shared_words_weigh_nothing():
    words = [np.array([0, 1, 1]), np.array([0, 2]), np.array([0]), np.array([], dtype=np.int64)]
    v = tfidf(words, vocabulary=3)
    assert np.allclose(np.linalg.norm(v[:3], axis=1), 1.0) and not v[3].any()  # no word: zeros
    assert 0 < v[0, 0] < v[0, 1]  # word 0 is in 3 of 4 frames: weighed less than word 1 (one frame)
    v = tfidf(words[:3], vocabulary=3)  # now in every frame: idf 0, it says nothing
    assert v[0, 0] == 0.0 and v[0, 1] > 0 and v[1, 2] > 0


def test_retrieval_pairs_link_frames_that_share_words():
    """Frames along a corridor see words of their neighbours: retrieval pairs them with those
    neighbours, whatever their order in the folder."""
    rng = np.random.default_rng(3)
    order = rng.permutation(30)  # file order says nothing
    words = []
    for position in order:
        # frame at position p sees words p-2..p+2 of a 40-word world, plus clutter shared by all
        seen = np.arange(position - 2, position + 3) % 40
        words.append(np.concatenate([np.repeat(seen, 5), rng.integers(40, 50, size=10)]))
    pairs = retrieval_pairs(tfidf(words, 50), neighbours=2)
    index_of = {int(p): i for i, p in enumerate(order)}
    for p in range(1, 29):
        a, b = sorted((index_of[p], index_of[p + 1]))
        assert (a, b) in pairs  # every corridor neighbour is paired
    assert all(abs(int(order[a]) - int(order[b])) <= 4 for a, b in pairs)
    assert len({i for pair in pairs for i in pair}) == 30
    with pytest.raises(ValueError, match="neighbours"):
        retrieval_pairs(tfidf(words, 50), 0)
