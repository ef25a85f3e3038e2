"""The frame-to-frame map's compiled helpers against the numpy they replaced, bit for bit (the map compares
their values with gates: a last-bit difference could move an id), and the certainty rule's shortcuts (a settled
merge of two readings, the consistency test of a grown reading) against the work they skip."""

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


def test_k_nearest_points_equal_the_k_d_trees():
    """Random point sets of 1-300 points and queries (some on the points, some rounded to integers, k up to
    15, more than the points in some): the distances and indices cKDTree's query gives, bit for bit where no
    two points tie (a k-d tree keeps an arbitrary one of tied points; :func:`knn` the lower index)."""
    from pipeline.vision.nearest import knn

    rng = np.random.default_rng(2)
    for t in range(1500):
        n, q, k = int(rng.integers(1, 300)), int(rng.integers(1, 100)), int(rng.integers(2, 16))
        pts = rng.uniform(0.0, 640.0, (n, 2))
        queries = rng.uniform(-20.0, 660.0, (q, 2))
        if t % 3 == 0:
            queries[:min(q, n)] = pts[:min(q, n)]
        if t % 7 == 0:
            queries = np.round(queries)
        d, j = cKDTree(pts).query(queries, k=k)
        dk, jk = knn(pts, queries, k)
        assert dk.tobytes() == d.tobytes() and np.array_equal(jk, j)
    # ties: the lower index first, at the same distance
    pts = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [5.0, 5.0]])
    d, j = knn(pts, np.zeros((1, 2)), 5)
    assert j.tolist() == [[0, 1, 2, 3, 4]] and d[0, :4].tolist() == [1.0] * 4


def _apart_numpy(P, prev_ids, pred, jac, which, known, design_nbr, design_xy, pts, s_prev):
    """The lost-neighbours test as numpy's least squares and a k-d tree give it (the definition)."""
    from pipeline.vision.identity.apart import F2F_APART

    tree = cKDTree(pts)
    out = np.zeros(len(P), bool)
    row = np.full(len(known), -1, np.int64)
    row[prev_ids] = np.arange(len(prev_ids))
    for i in np.flatnonzero(which):
        me = prev_ids[i]
        nbrs = design_nbr[me][design_nbr[me] >= 0]
        have, missing = nbrs[known[nbrs]], nbrs[~known[nbrs]]
        if len(have) < 2 or len(missing) == 0:
            continue
        dD = design_xy[have] - design_xy[me]
        if np.linalg.matrix_rank(dD, tol=1e-6 * float(np.abs(dD).max())) < 2:
            continue
        A = np.linalg.lstsq(dD, P[row[have]] - P[i], rcond=None)[0]
        q = pred[i] + ((design_xy[missing] - design_xy[me]) @ A) @ jac[i].reshape(2, 2).T
        d, j = tree.query(q)
        out[i] = bool(np.all((j != tree.query(pred[i])[1]) & (d <= F2F_APART * s_prev[i])))
    return out


def test_lost_neighbours_apart_decides_as_least_squares_and_a_k_d_tree_do():
    """The compiled test against its numpy definition on a design's lattice seen through random affine maps
    and noise, with random markers lost from the previous frame, blobs missing now and spurious blobs added
    (some right where a lost neighbour is put, some a spacing off): the same markers stand apart, and both
    outcomes occur."""
    from pipeline.design import load_design
    from pipeline.vision.identity import lattice_of
    from pipeline.vision.identity.apart import lost_neighbours_apart

    rng = np.random.default_rng(3)
    seen = [0, 0]
    for name in ("hexagon127", "square121", "circular217_dome"):
        lat = lattice_of(load_design(name))
        n_slots = len(lat.xy)
        for _ in range(60):
            A = np.eye(2) * rng.uniform(8.0, 14.0) + rng.normal(0.0, 1.5, (2, 2))
            img = lat.xy @ A.T + rng.uniform(100.0, 400.0, 2)
            spacing = float(np.median(np.linalg.norm(lat.xy[lat.nbr[:, 0]] - lat.xy, axis=1))) * abs(np.linalg.det(A)) ** 0.5
            known = np.ones(n_slots + 1, bool)
            known[rng.choice(n_slots, int(rng.integers(1, n_slots // 5)), replace=False)] = False
            prev_ids = np.flatnonzero(known[:-1])
            P = img[prev_ids] + rng.normal(0.0, 0.03 * spacing, (len(prev_ids), 2))
            step = rng.normal(0.0, 0.1 * spacing, 2)
            now = img + step + rng.normal(0.0, 0.05 * spacing, img.shape)
            keep = rng.random(n_slots) > rng.uniform(0.0, 0.2)
            extra = now[rng.choice(n_slots, int(rng.integers(0, 15)))] + rng.normal(0.0, rng.choice([0.05, 0.5]) * spacing, (1, 2))
            pts = np.vstack([now[keep], extra])
            pred = P + step
            jac = np.tile(np.eye(2).ravel() + rng.normal(0.0, 0.02, 4), (len(P), 1))
            which = rng.random(len(P)) < 0.7
            s_prev = np.full(len(P), spacing) * rng.uniform(0.8, 1.2, len(P))
            args = (P, prev_ids, pred, jac, which, known, lat.nbr, lat.xy, pts, s_prev)
            got = lost_neighbours_apart(*args)
            np.testing.assert_array_equal(got, _apart_numpy(*args))
            lost_nbr = (~known[lat.nbr[prev_ids]] & (lat.nbr[prev_ids] >= 0)).any(axis=1) & which
            seen[0] += int((got & lost_nbr).sum())
            seen[1] += int((~got & lost_nbr).sum())
    assert min(seen) > 50, seen


def test_a_settled_reading_is_what_certifying_its_merge_again_gives(monkeypatch):
    """A reading of a view with missing and spurious blobs is certified once from ring coding's proposal and once
    from the ids carried from the previous frame, and the two are merged and certified again, unless the merge is
    settled (:func:`pipeline.vision.dtrc.proposals._settled`: it adds nothing, certification withdrew nothing and
    growth proposes no blob). Wherever it says so over a press sequence of three patterns with 1-5 % defects per
    frame, certifying the merge again gives the same ids, and it says so often."""
    import pipeline.vision.dtrc.proposals as proposals
    from pipeline.vision.identity import certify, consistent, grow

    checked = [0, 0]
    settled = proposals._settled

    def checking(pts, best, merged, lat):
        out = settled(pts, best, merged, lat)
        checked[1] += 1
        if out:
            r = np.zeros(len(lat.xy), np.int64)
            again = certify(pts, grow(pts, consistent(pts, merged, lat, r), lat, r), lat, r)
            np.testing.assert_array_equal(again, best[0])
            checked[0] += 1
        return out

    monkeypatch.setattr(proposals, "_settled", checking)
    from benchmarks.experiments.identification import add_defects, view_px
    from pipeline.design import load_design
    from pipeline.types import Blobs
    from pipeline.vision.dtrc import DTRCTracker

    for name, rate in (("hexagon127", 0.01), ("square121", 0.03), ("circular217_dome", 0.05)):
        design = load_design(name)
        rng = np.random.default_rng(11)
        rest = view_px(design, rng)
        tracker = DTRCTracker(design)
        for k, t in enumerate(np.linspace(0.0, 1.0, 8)):
            views = [add_defects(rest - offset + t * np.array([6.0, -4.0]) + rng.normal(0.0, 0.2, rest.shape), rng,
                                 missing=rate if k else 0.0, spurious=rate if k else 0.0)[0]
                     for offset in ([0.0, 0.0], [25.0, 0.0])]
            tracker.update(*(Blobs(v, np.full(len(v), 3.0), np.ones(len(v))) for v in views))
    assert checked[0] >= 10 and checked[0] >= checked[1] // 2, checked


def test_growth_returns_a_consistent_reading_so_certification_may_skip_its_first_test():
    """``certify(..., consistent_input=True)`` skips the consistency test of its first pass on what growth returned
    (a reading the test passes unchanged). Over views of four patterns with 0-10 % missing and spurious blobs read
    by ring coding: growth's output passes the test unchanged, and certifying it with and without the skip gives the
    same ids and the same reasons."""
    from benchmarks.experiments.identification import add_defects, view_px
    from pipeline.design import load_design
    from pipeline.types import Blobs
    from pipeline.vision.dtrc import code_rings
    from pipeline.vision.identity import certify, consistent, grow, lattice_of

    rng = np.random.default_rng(5)
    grown_some = 0
    for name in ("hexagon127", "square121", "circular217_dome", "hexagon217_sep180"):
        design = load_design(name)
        lat = lattice_of(design)
        for rate in (0.0, 0.03, 0.1):
            for _ in range(4):
                pts = add_defects(view_px(design, rng), rng, missing=rate, spurious=rate)[0]
                proposal = code_rings(Blobs(pts, np.full(len(pts), 3.0), np.ones(len(pts))), design).ids
                r = np.zeros(len(lat.xy), np.int64)
                start = consistent(pts, proposal, lat, r)
                grown = grow(pts, start, lat, r)
                grown_some += int(np.count_nonzero(grown >= 0) > np.count_nonzero(start >= 0))
                np.testing.assert_array_equal(consistent(pts, grown, lat, r.copy()), grown)
                r1, r2 = r.copy(), r.copy()
                np.testing.assert_array_equal(certify(pts, grown, lat, r1, consistent_input=True),
                                              certify(pts, grown, lat, r2))
                np.testing.assert_array_equal(r1, r2)
    assert grown_some > 0
