"""The compiled detection passes for crowded markers against their numpy definitions.

The definitions below are the code as first written in numpy: the pair tests (``pair_profiles``: a blob's window,
its long axis, the dark line between touching pins, the waist of overlapping ones) and the touching-marker
screens (``crowding``: ring sectors lit by a touching peer, candidates flanked on opposite sides, centroids with
a neighbour's light left out). Detection outputs depend on every bit (the tests compare floats against
thresholds), so each compiled pass must give the same result bit for bit on every candidate the detector
examines: on the twin's crowded crest and the real TacTip frames.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import median_filter
from scipy.spatial import cKDTree

from pipeline.vision.detection import DetectionParams, detect_markers
from pipeline.vision.detection import crowding as C
from pipeline.vision.detection import rejection as R
from pipeline.vision.detection import pair_profiles as K
from pipeline.vision.detection import pairs as P
from pipeline.vision.detection.candidates import SIGMA
from pipeline.vision.detection.images import U8_SCALE
from pipeline.vision.detection.numpy_order import arange, float_sum
from pipeline.vision.detection.photometry import RING_IN, RING_WIDTH_PX, RUNAWAY_FRACTION, RUNAWAY_PX, SECTORS, \
    WINDOW_MARGIN_PX

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_frames"
CROWDED = Path(__file__).resolve().parent / "data" / "sine_crowded_pins_hexagon217_sep180.npz"


def _bilinear(patch, x, y):
    h, w = patch.shape
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2) if w > 1 else np.zeros(len(x), np.intp)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2) if h > 1 else np.zeros(len(y), np.intp)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return ((patch[y0, x0] * (1 - fx) + patch[y0, x1] * fx) * (1 - fy)
            + (patch[y1, x0] * (1 - fx) + patch[y1, x1] * fx) * fy)


class _Window:
    """A blob's window: pixels within it, weights above the background (10th percentile), centroid, long axis."""

    @classmethod
    def of(cls, grey, centre, r, r_win):
        h, w = grey.shape
        x0, y0 = float(centre[0]), float(centre[1])
        xa, xb = max(0, int(np.floor(x0 - r_win))), min(w - 1, int(np.ceil(x0 + r_win)))
        ya, yb = max(0, int(np.floor(y0 - r_win))), min(h - 1, int(np.ceil(y0 + r_win)))
        if xb - xa < 2 or yb - ya < 2:
            return None
        self = cls()
        self.patch = grey[ya:yb + 1, xa:xb + 1].astype(np.float64)
        gx = np.arange(xa, xb + 1, dtype=np.float64)[None, :]
        gy = np.arange(ya, yb + 1, dtype=np.float64)[:, None]
        inside = (gx - x0) ** 2 + (gy - y0) ** 2 <= r_win * r_win
        v = self.patch[inside]
        self.px = np.broadcast_to(gx, self.patch.shape)[inside]
        self.py = np.broadcast_to(gy, self.patch.shape)[inside]
        k_bg = int(len(v) * K.BACKGROUND_PERCENTILE / 100)
        self.bg = float(np.partition(v, k_bg)[k_bg])
        self.wt = np.maximum(v - self.bg, 0.0)
        tot = self.wt.sum()
        if tot <= 0:
            return None
        self.cx, self.cy = (self.wt * self.px).sum() / tot, (self.wt * self.py).sum() / tot
        dx, dy = self.px - self.cx, self.py - self.cy
        sxx, syy, sxy = (self.wt * dx * dx).sum(), (self.wt * dy * dy).sum(), (self.wt * dx * dy).sum()
        ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        self.ux, self.uy = np.cos(ang), np.sin(ang)
        self.xa, self.ya, self.r = xa, ya, r
        return self

    def sample(self, t, o):
        o = np.asarray(o, np.float64)[:, None]
        vals = _bilinear(self.patch, (self.cx - self.xa + t * self.ux - o * self.uy).ravel(),
                         (self.cy - self.ya + t * self.uy + o * self.ux).ravel())
        return vals.reshape(len(o), len(t)) - self.bg


def _line_pins(win, min_apart):
    t = np.arange(-win.r, win.r + 1e-9, K.STEP_PX)
    prof = win.sample(t, K.ACROSS_PX).mean(axis=0)
    neg, pos = t < 0, t > 0
    if not (neg.any() and pos.any()):
        return None
    a = int(np.argmax(np.where(neg, prof, -np.inf)))
    c = int(np.argmax(np.where(pos, prof, -np.inf)))
    low = min(prof[a], prof[c])
    if low < P.PAIR_PEAK_FRACTION * prof.max() or t[c] - t[a] < min_apart or prof[a:c + 1].min() > P.PAIR_DIP * low:
        return None
    side = (win.px - win.cx) * win.ux + (win.py - win.cy) * win.uy
    halves = []
    for half in (side < 0, side >= 0):
        hw = win.wt[half]
        if hw.sum() > 0:
            halves.append(np.array([(hw * win.px[half]).sum() / hw.sum(), (hw * win.py[half]).sum() / hw.sum()]))
    return halves if len(halves) == 2 else None


def _waist_pins(win, min_apart):
    reach = win.r + 0.5 * min_apart
    t = np.arange(-reach, reach + 1e-9, K.STEP_PX)
    o = np.arange(-win.r, win.r + 1e-9, K.STEP_PX)
    light = win.sample(t, o)
    c0 = len(o) // 2
    above = light > 0.5 * float(win.wt.max())
    hi = np.argmin(np.vstack([above[c0:], np.zeros((1, len(t)), bool)]), axis=0)
    lo = np.argmin(np.vstack([above[c0::-1], np.zeros((1, len(t)), bool)]), axis=0)
    width = np.where(above[c0], (hi + lo - 1) * K.STEP_PX, 0.0)
    width = median_filter(width, size=3, mode="nearest")
    mid = (hi - lo) * K.STEP_PX / 2
    neg, pos = t < 0, t > 0
    if not (neg.any() and pos.any()):
        return None
    wa, wc = width[neg].max(), width[pos].max()
    if min(wa, wc) <= 0 or min(wa, wc) < P.PAIR_PEAK_FRACTION * max(wa, wc):
        return None
    if max(width[0] / wa, width[-1] / wc) > P.PAIR_END_FRACTION:
        return None
    pa = neg & (width >= 0.95 * wa)
    pc = pos & (width >= 0.95 * wc)
    ta, tc = float(t[pa].mean()), float(t[pc].mean())
    between = (t > t[pa].max()) & (t < t[pc].min())
    if tc - ta < min_apart or not between.any() or width[between].min() > P.PAIR_WAIST * min(wa, wc):
        return None
    return [np.array([win.cx + tt * win.ux - oo * win.uy, win.cy + tt * win.uy + oo * win.ux])
            for tt, oo in ((ta, float(mid[pa].mean())), (tc, float(mid[pc].mean())))]


def _reference(grey, xs, ys, rs, r_wins, min_aparts, dark, waist):
    found = np.zeros(len(xs), bool)
    pins = np.zeros((len(xs), 2, 2))
    for k in range(len(xs)):
        win = _Window.of(grey, (xs[k], ys[k]), rs[k], r_wins[k])
        if win is None:
            continue
        got = _line_pins(win, min_aparts[k]) if dark[k] else None
        if got is None and waist[k]:
            got = _waist_pins(win, min_aparts[k])
        if got is not None:
            found[k], pins[k] = True, got
    return found, pins


def _ring_spread(xy: np.ndarray, radius: np.ndarray, sectors: np.ndarray, peers: np.ndarray,
                 examine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    spread = sectors.max(axis=1)
    crowded = np.zeros(len(xy), dtype=bool)
    idx = np.nonzero(peers)[0]
    if len(idx) < 2 or not examine.any():
        return spread, crowded
    tree = cKDTree(xy[idx])
    reach = RING_IN * radius + RING_WIDTH_PX
    centres = -np.pi + (np.arange(SECTORS) + 0.5) * (2 * np.pi / SECTORS)
    for i in np.nonzero(examine)[0]:
        near = [idx[j] for j in tree.query_ball_point(xy[i], reach[i] + radius.max()) if idx[j] != i]
        near = [j for j in near if np.hypot(*(xy[j] - xy[i])) <= reach[i] + radius[j]]
        if not near:
            continue
        crowded[i] = True
        d = xy[near] - xy[i]
        ang = np.arctan2(d[:, 1], d[:, 0])
        off = np.abs((centres[None, :] - ang[:, None] + np.pi) % (2 * np.pi) - np.pi)
        masked = (off < C.PEER_HALF_ANGLE_RAD).any(axis=0)
        if masked.sum() <= SECTORS // 2:
            spread[i] = sectors[i, ~masked].max()
    return spread, crowded


def _flanked(xy: np.ndarray, radius: np.ndarray, which: np.ndarray, peers: np.ndarray) -> np.ndarray:
    out = np.zeros(len(xy), bool)
    idx = np.nonzero(peers)[0]
    if len(idx) < 2 or not which.any():
        return out
    tree = cKDTree(xy[idx])
    reach = RING_IN * radius + RING_WIDTH_PX
    for i in np.nonzero(which)[0]:
        near = [idx[j] for j in tree.query_ball_point(xy[i], reach[i] + radius.max()) if idx[j] != i]
        near = [j for j in near if np.hypot(*(xy[j] - xy[i])) <= reach[i] + radius[j]]
        if len(near) < 2:
            continue
        d = xy[near] - xy[i]
        ang = np.arctan2(d[:, 1], d[:, 0])
        gap = np.abs((ang[:, None] - ang[None, :] + np.pi) % (2 * np.pi) - np.pi)
        out[i] = bool((gap >= C.FLANK_MIN_ANGLE_RAD).any())
    return out


def _split_centroids(grey: np.ndarray, xy: np.ndarray, radius: np.ndarray, which: np.ndarray,
                     peers: np.ndarray, params: DetectionParams) -> np.ndarray:
    out = xy.copy()
    if not which.any():
        return out
    idx = np.nonzero(peers)[0]
    tree = cKDTree(xy[idx])
    h, w = grey.shape
    for i in np.nonzero(which)[0]:
        r = float(radius[i])
        r_win = params.centroid_radius_factor * r + WINDOW_MARGIN_PX
        nb = [idx[j] for j in tree.query_ball_point(xy[i], 2 * r_win) if idx[j] != i]
        c = xy[i].copy()
        for _ in range(max(1, params.centroid_iterations)):
            x0, x1 = int(max(0, np.floor(c[0] - r_win))), int(min(w - 1, np.ceil(c[0] + r_win)))
            y0, y1 = int(max(0, np.floor(c[1] - r_win))), int(min(h - 1, np.ceil(c[1] + r_win)))
            gx, gy = np.meshgrid(np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64))
            d2 = (gx - c[0]) ** 2 + (gy - c[1]) ** 2
            own = d2 <= r_win * r_win
            for j in nb:
                own &= d2 < (gx - xy[j, 0]) ** 2 + (gy - xy[j, 1]) ** 2
            v = (grey[y0:y1 + 1, x0:x1 + 1] * U8_SCALE).astype(np.float64)
            ring = own & (d2 >= (RING_IN * r) ** 2)
            bg = float(np.median(v[ring])) if ring.any() else 0.0
            wts = np.where(own, np.maximum(v - bg, 0.0), 0.0)
            tot = wts.sum()
            if tot <= 0:
                break
            new = np.array([(wts * gx).sum() / tot, (wts * gy).sum() / tot])
            if np.hypot(*(new - xy[i])) > RUNAWAY_FRACTION * r + RUNAWAY_PX:
                break
            c = new
        out[i] = c
    return out


def _inside_hull(xy, ref):
    from scipy.spatial import Delaunay, QhullError

    if len(ref) < 3:
        return np.zeros(len(xy), bool)
    spacing = float(np.median(cKDTree(ref).query(ref, k=2)[0][:, 1]))
    c = ref.mean(axis=0)
    r = np.maximum(np.hypot(*(ref - c).T), 1e-9)[:, None]
    grown = c + (ref - c) * (1.0 + 0.5 * spacing / r)
    try:
        return Delaunay(grown).find_simplex(xy) >= 0
    except QhullError:
        return np.zeros(len(xy), bool)


def _ring_background(grey, xy, radius):
    from pipeline.vision.detection.photometry import group_offsets

    h, w = grey.shape
    out = np.full(len(xy), np.nan)
    for i, ((u, v), r) in enumerate(zip(xy, radius)):
        dx, dy = group_offsets(float(r), DetectionParams())[:2]
        x, y = int(np.rint(u)) + dx, int(np.rint(v)) + dy
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        if ok.any():
            out[i] = float(np.median(grey[y[ok], x[ok]])) / 255.0
    return out


def _local_scale(cand, typical, which):
    ref = np.flatnonzero(typical)
    out = np.full(int(which.sum()), np.inf)
    if len(ref) < R.LOCAL_SIZE_NEIGHBOURS + 1:
        return out
    xy = cand[:, :2]
    _, j = cKDTree(xy[ref]).query(xy[which], k=R.LOCAL_SIZE_NEIGHBOURS + 1)
    for r, (i, row) in enumerate(zip(np.flatnonzero(which), j)):
        nb = ref[row]
        out[r] = float(np.median(cand[nb[nb != i][:R.LOCAL_SIZE_NEIGHBOURS], SIGMA]))
    return out


def _spacing_suppress(xy, response, fraction):
    tree = cKDTree(xy)
    d, _ = tree.query(xy, k=2)
    radius = fraction * float(np.median(d[:, 1]))
    keep = np.ones(len(xy), bool)
    for i in np.argsort(-response, kind="stable"):
        if not keep[i]:
            continue
        for j in tree.query_ball_point(xy[i], radius):
            if j != i and keep[j] and np.hypot(*(xy[j] - xy[i])) < radius:
                keep[j] = False
    return keep


def _views():
    views = [np.load(CROWDED)["image"]]
    views += [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(DATA.glob("tactip331_tap_*.png"))[:12]]
    return views


def test_pair_profiles_equal_their_numpy_definitions_on_every_blob_examined(monkeypatch):
    """Every blob the detector profiles (the crowded crest's pairs; on the real frames, where present, the
    elongated markers at a pair's scale, ~15 a view) gives the same verdict and the same pins bit for bit."""
    calls = []

    def recorded(grey, *args):
        out = K.pair_pins(grey, *args)
        calls.append((grey.copy(), [np.array(a, copy=True) for a in args], out))
        return out

    monkeypatch.setattr(P, "pair_pins", recorded)
    views = _views()
    for view in views:
        detect_markers(view)
    examined = sum(len(a[0]) for _, a, _ in calls)
    split = sum(int(out[0].sum()) for _, _, out in calls)
    assert split >= 3 and examined >= (100 if len(views) > 1 else 3)
    for grey, args, (found, pins) in calls:
        ref_found, ref_pins = _reference(grey, *args[:7])
        assert np.array_equal(found, ref_found)
        assert pins[found].tobytes() == ref_pins[found].tobytes()


def test_the_kernels_sums_and_ranges_are_numpys():
    """The kernels' float ranges and sums (``_arange``, ``_sum``: pairwise, eight accumulators, halves a
    multiple of eight long) equal np.arange and ndarray.sum bit for bit, across the block sizes."""
    rng = np.random.default_rng(3)
    for n in [*range(0, 140), 255, 256, 257, 900, 2049]:
        a = rng.standard_normal(n) * 10.0 ** rng.integers(-3, 4)
        assert np.float64(float_sum(a)).tobytes() == np.float64(a.sum()).tobytes()
    for start in -rng.uniform(0.0, 15.0, 300):
        assert np.array_equal(arange(start, -start + 1e-9, K.STEP_PX), np.arange(start, -start + 1e-9, K.STEP_PX))


def test_a_window_at_the_image_corner_or_without_light_is_skipped():
    """A blob whose window is cut to under three pixels by the image edge, or holds no light above its
    background, is left as it is (not found), as the definition leaves it."""
    grey = np.full((40, 40), 30, np.uint8)
    grey[10:20, 10:20] = 200
    xs, ys = np.array([0.2, 20.0]), np.array([0.3, 30.0])
    args = (xs, ys, np.array([4.0, 4.0]), np.array([0.5, 6.0]), np.array([4.0, 4.0]), np.array([True, True]),
            np.array([True, True]))
    found, _ = K.pair_pins(grey, *args, P.PAIR_PEAK_FRACTION, P.PAIR_DIP, P.PAIR_WAIST, P.PAIR_END_FRACTION)
    assert not found.any()
    assert not _reference(grey, *args)[0].any()


def test_touching_marker_screens_equal_their_numpy_definitions(monkeypatch):
    """Every call the detector makes to the ring-sector and split-centroid screens (the crowded crest; the real
    frames, where present: ~30 candidates a view examined, ~10 re-centred) gives the same result bit for bit as
    the numpy definitions."""
    calls = []
    for name in ("ring_spread", "split_centroids"):
        def recorded(*args, _f=getattr(R, name), _n=name):
            out = _f(*args)
            calls.append((_n, [a if isinstance(a, DetectionParams) else np.array(a, copy=True) for a in args], out))
            return out
        monkeypatch.setattr(R, name, recorded)
    for view in _views():
        detect_markers(view)
    assert sum(int(a[4].sum()) for n, a, _ in calls if n == "ring_spread") >= 3
    assert sum(int(a[3].sum()) for n, a, _ in calls if n == "split_centroids") >= 3
    for name, args, out in calls:
        if name == "ring_spread":
            ref = _ring_spread(*args)
            assert out[0].tobytes() == ref[0].tobytes() and np.array_equal(out[1], ref[1])
        else:
            assert out.tobytes() == _split_centroids(*args).tobytes()


def test_flanked_candidates_equal_their_numpy_definition():
    """Random crowds of candidates (some squeezed between two peers, some touching one): the same candidates
    are flanked as by the numpy definition, and some are."""
    rng = np.random.default_rng(8)
    n_flanked = 0
    for _ in range(200):
        n = int(rng.integers(3, 40))
        xy = rng.uniform(0, 60, (n, 2))
        radius = rng.uniform(2.0, 6.0, n)
        which, peers = rng.random(n) < 0.5, rng.random(n) < 0.7
        got = C.flanked(xy, radius, which, peers)
        assert np.array_equal(got, _flanked(xy, radius, which, peers))
        n_flanked += int(got.sum())
    assert n_flanked > 20


def test_the_marker_field_screens_equal_their_numpy_definitions(monkeypatch):
    """With the monocular dome's parameters (debris, the marker field's hull, the ring background, spacing) every
    call the detector makes on the crowded crest and the real frames (where present) gives the same result bit
    for bit as the numpy definitions: the field inside the grown hull of the strict markers (Qhull's triangulation
    there, its hull's facets here), the ring background medians, each small candidate's local size, the spacing
    suppression."""
    from pipeline.vision.detection import MONOCULAR_DOME
    from pipeline.vision.detection import detect as D

    calls = []
    for mod, name, ref in ((R, "_inside_hull", _inside_hull), (R, "_ring_background", _ring_background),
                           (R, "_local_scale", _local_scale), (D, "spacing_suppress", _spacing_suppress)):
        def recorded(*args, _f=getattr(mod, name), _ref=ref):
            out = _f(*args)
            calls.append((_ref, [np.array(a, copy=True) for a in args], out))    # the caller edits its masks
            return out
        monkeypatch.setattr(mod, name, recorded)
    for view in _views():
        detect_markers(view, params=MONOCULAR_DOME)
    assert {ref.__name__ for ref, _, _ in calls} == {"_inside_hull", "_ring_background", "_local_scale",
                                                      "_spacing_suppress"}
    assert sum(int(out.sum()) for ref, _, out in calls if ref is _inside_hull) >= 100
    for ref, args, out in calls:
        assert np.asarray(out).tobytes() == np.asarray(ref(*args)).tobytes(), ref.__name__
