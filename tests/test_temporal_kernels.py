"""The frame-to-frame map's compiled helpers against the numpy they replaced, bit for bit (the map compares
their values with gates: a last-bit difference could move an id)."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree

from pipeline.vision.identity.temporal import _median_where, _nn_dist


def _median_where_numpy(v, mask, default):
    w = np.where(mask, v, np.nan)
    out = default.copy()
    has = mask.any(axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # a row of NaN only: NaN, as the kernel gives
        out[has] = np.nanmedian(w[has], axis=1)
    return out


def test_row_medians_over_a_mask_equal_numpys_nanmedian():
    """Rows of 1-12 spacings, some infinite or NaN, a random mask: the same medians as np.nanmedian of the row
    with the unmasked entries NaN (the default where nothing is masked in)."""
    rng = np.random.default_rng(0)
    for k in range(1500):
        n, width = int(rng.integers(1, 60)), int(rng.integers(1, 13))
        v = rng.uniform(0.5, 30.0, (n, width)) * rng.choice([1.0, 1.0, 1.0, np.inf], (n, width))
        if k % 3 == 0:
            v[rng.random((n, width)) < 0.1] = np.nan
        mask = rng.random((n, width)) < rng.uniform(0.0, 1.0)
        default = rng.uniform(1.0, 2.0, n)
        assert _median_where(v, mask, default).tobytes() == _median_where_numpy(v, mask, default).tobytes()


def test_nearest_neighbour_distances_equal_the_k_d_trees():
    """Random point sets of 1-300 points, with duplicated points and integer ties: each point's distance to
    its nearest other point as cKDTree's query gives it (inf for a lone point), bit for bit."""
    rng = np.random.default_rng(1)
    for k in range(1500):
        n = int(rng.integers(1, 300))
        xy = rng.uniform(0.0, 640.0, (n, 2))
        if k % 5 == 0 and n > 3:
            xy[1] = xy[0]
        if k % 7 == 0:
            xy = np.round(xy)
        d = cKDTree(xy).query(xy, k=2)[0][:, 1]
        assert _nn_dist(xy).tobytes() == np.where(np.isfinite(d), d, np.inf).tobytes()
