"""The SIFT matcher's fast path (`_mutual_ratio_matches` on squared distances) against the plain full-matrix one."""

from __future__ import annotations

import numpy as np
import pytest

from gpdepth3d.mapping.points.features import (
    Features,
    _mutual_ratio_matches,
    _squared_descriptor_distances,
    match_features,
)
from gpdepth3d.mapping.points.triangulation_config import TriangulationConfig


def _plain_matches(da: np.ndarray, db: np.ndarray, ratio: float) -> np.ndarray:
    """The mutual ratio test written out on the full distance matrix (partition for the two nearest)."""
    sq = np.einsum("ij,ij->i", da, da)[:, None] + np.einsum("ij,ij->i", db, db)[None, :] - 2.0 * (da @ db.T)
    dist = np.sqrt(np.maximum(sq, 0.0))
    nearest = np.argpartition(dist, 1, axis=1)[:, :2]
    d2 = np.take_along_axis(dist, nearest, axis=1)
    j = nearest[np.arange(len(dist)), np.argmin(d2, axis=1)]
    i = np.arange(len(dist))
    keep = (d2.min(axis=1) < ratio * d2.max(axis=1)) & (np.argmin(dist, axis=0)[j] == i)
    return np.column_stack([i[keep], j[keep]]).astype(np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("ratio", [0.6, 0.8, 1.0])
def test_fast_mutual_ratio_matches_equal_the_full_distance_matrix(seed, ratio):
    """Same pairs as the full-matrix test, also with duplicated descriptors (ties at the nearest, both ways)."""
    rng = np.random.default_rng(seed)
    da = rng.integers(0, 8, (400, 16)).astype(np.float32)  # few values: many exactly tied distances
    db = np.vstack([da[:200] + rng.integers(-1, 2, (200, 16)), da[:50], rng.integers(0, 8, (150, 16))])
    db = db.astype(np.float32)
    a, b = Features(np.zeros((400, 2)), da, "sift"), Features(np.zeros((400, 2)), db, "sift")
    sq = _squared_descriptor_distances(a, b)
    before = sq.copy()
    fast = _mutual_ratio_matches(sq, ratio)
    assert np.array_equal(sq, before)  # the matrix is given back as it came
    expected = _plain_matches(da, db, ratio)
    assert fast.dtype == np.int64 and fast.shape[1] == 2
    assert np.array_equal(fast, expected)
    assert len(expected) > 20  # the test compares real matches, not two empty lists


def test_match_features_sift_equals_the_full_distance_matrix_on_sift_like_descriptors():
    """Whole `match_features` (no epipolar gate) on SIFT-like float descriptors gives the plain test's pairs."""
    rng = np.random.default_rng(7)
    da = rng.gamma(1.0, 30.0, (900, 128)).astype(np.float32)
    db = np.vstack([da[:500] + rng.normal(0, 8, (500, 128)), rng.gamma(1.0, 30.0, (700, 128))]).astype(np.float32)
    a, b = Features(rng.uniform(0, 300, (900, 2)), da, "sift"), Features(rng.uniform(0, 300, (1200, 2)), db, "sift")
    pairs = match_features(a, b, config=TriangulationConfig(ratio=0.8))
    assert np.array_equal(pairs, _plain_matches(da, db, 0.8))
    assert len(pairs) > 300


def test_integer_descriptors_take_one_product_with_the_three_step_values_bit_for_bit():
    """SIFT-like integer descriptors (OpenCV's) go through the augmented product; its values are the plain ones."""
    from gpdepth3d.mapping.points.features import EXACT_NORM2, _exactly_held, _integer_squared_distances

    rng = np.random.default_rng(11)
    da = rng.integers(0, 160, (700, 128)).astype(np.float32)
    da *= np.minimum(1.0, np.sqrt(EXACT_NORM2 / np.einsum("ij,ij->i", da, da)))[:, None] * 0.5
    da = np.rint(da)  # integer values, squared norms within the bound (as SIFT's ~512^2)
    db = np.rint(da[::-1] * 0.9 + rng.integers(-3, 4, da.shape)).clip(0).astype(np.float32)
    na, nb = np.einsum("ij,ij->i", da, da), np.einsum("ij,ij->i", db, db)
    assert _exactly_held(da, na) and _exactly_held(db, nb)
    plain = (na[:, None] + nb[None, :]) - 2.0 * (da @ db.T)
    assert np.array_equal(_integer_squared_distances(da, na, db, nb), plain)
    a, b = Features(np.zeros((700, 2)), da, "sift"), Features(np.zeros((700, 2)), db, "sift")
    assert np.array_equal(_squared_descriptor_distances(a, b), plain)
    # not integers, or norms beyond the bound: the three-step path (same formula, rounded as before)
    assert not _exactly_held(da + 0.25, np.einsum("ij,ij->i", da + 0.25, da + 0.25))
    big = np.full((3, 128), 200.0, np.float32)
    assert not _exactly_held(big, np.einsum("ij,ij->i", big, big))


def test_match_features_is_descriptor_matches_then_the_epipolar_gate():
    """The two halves give the whole: pose-free matches first, the gate of F (Sampson distance) after."""
    from gpdepth3d.errors import InvalidInputError
    from gpdepth3d.mapping.points.features import descriptor_matches, epipolar_gate, sampson_distance

    rng = np.random.default_rng(5)
    da = rng.integers(0, 60, (300, 128)).astype(np.float32)
    db = (da + rng.integers(-2, 3, da.shape)).clip(0).astype(np.float32)
    uv = rng.uniform(0, 200, (300, 2))
    a, b = Features(uv, da, "sift"), Features(uv + rng.normal(0, 3, (300, 2)), db, "sift")
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # pure x translation: epipolar lines v = v'
    config = TriangulationConfig(ratio=0.8, max_epipolar_error=2.0)
    raw = descriptor_matches(a, b, ratio=0.8)
    gated = epipolar_gate(raw, a, b, F, 2.0)
    err = sampson_distance(F, a.uv[raw[:, 0]], b.uv[raw[:, 1]])
    assert len(raw) > 200 and 0 < len(gated) < len(raw)
    assert np.array_equal(gated, raw[err <= 2.0])
    assert np.array_equal(match_features(a, b, config=config, F=F), gated)
    assert np.array_equal(match_features(a, b, config=config), raw)
    assert np.array_equal(epipolar_gate(raw, a, b, None, 2.0), raw)
    with pytest.raises(InvalidInputError, match="b"):
        descriptor_matches(a, Features(uv, da[:, :32].astype(np.uint8), "orb"))
    with pytest.raises(InvalidInputError, match="klt"):
        descriptor_matches(Features(uv, np.zeros((300, 0), np.float32), "klt"), b)
