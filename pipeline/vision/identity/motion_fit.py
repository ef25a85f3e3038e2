"""The frame-to-frame map's local affine fit of the neighbours' motion (:func:`_predict`), compiled.

Shared by frame-to-frame certification (:mod:`pipeline.vision.identity.temporal`), re-acquisition and the
carried places of lost markers (:mod:`pipeline.vision.identity.reacquire`): each marker's position in the
current frame predicted from how its neighbours moved, the marker itself never among them.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["_predict"]


@numba.njit(cache=True, nogil=True)
def _predict(P, pts, nb, near, corr, s_prev, min_fit, spread, max_residual, B):
    """Each previous marker's current position predicted by the affine map of its neighbours' motion
    (previous -> current positions of the neighbours ``nb`` within reach ``near`` that have a
    correspondence ``corr``), the marker itself excluded. Returns (prediction (M, 2), usable (M,)):
    usable when at least ``min_fit`` neighbours spread in two directions (smaller principal standard
    deviation >= ``spread`` local spacings) and the map fits every one of them to ``max_residual``
    local spacings; the previous position where not usable; the fitted map's Jacobian (M, 4)
    (previous -> current position, row-major; zero where not usable); and the worst neighbour's residual
    in local spacings (M,) (inf where not usable). ``B`` (M, 2): the base each motion is
    taken from (``P``: the frame's increment; the positions expected at the last velocity: the
    change of the increment), the prediction being the marker's base moved by the fitted motion.

    Not the sums of :mod:`pipeline.vision.identity.fits` on purpose: those are one-pass raw sums about an
    origin, kept so that every leave-one-out fit of a design neighbourhood is one subtraction and their
    design half can be tabulated per design; this fit is made once per marker (the marker is never among
    its own neighbours), so it takes the means first and then the centred moments (two passes, no
    cancellation) and tests the spread per point in local spacings (``spread``), where the design fits
    test the total scatter. Same map in exact arithmetic, different rounding and collinearity test: one
    routine for both would move borderline decisions."""
    m, k = nb.shape
    pred = P.copy()
    ok = np.zeros(m, np.bool_)
    jac = np.zeros((m, 4))
    res = np.full(m, np.inf)
    for i in range(m):
        n = 0
        sx = sy = su = sv = 0.0
        for q in range(k):
            j = nb[i, q]
            if near[i, q] and corr[j] >= 0:
                n += 1
                sx += P[j, 0] - P[i, 0]
                sy += P[j, 1] - P[i, 1]
                su += pts[corr[j], 0] - B[j, 0]
                sv += pts[corr[j], 1] - B[j, 1]
        if n < min_fit:
            continue
        mx, my, mu, mv = sx / n, sy / n, su / n, sv / n
        cxx = cxy = cyy = cux = cuy = cvx = cvy = 0.0
        for q in range(k):
            j = nb[i, q]
            if near[i, q] and corr[j] >= 0:
                x = P[j, 0] - P[i, 0] - mx
                y = P[j, 1] - P[i, 1] - my
                u = pts[corr[j], 0] - B[j, 0] - mu
                v = pts[corr[j], 1] - B[j, 1] - mv
                cxx += x * x
                cxy += x * y
                cyy += y * y
                cux += u * x
                cuy += u * y
                cvx += v * x
                cvy += v * y
        tr = (cxx + cyy) / n
        det = (cxx * cyy - cxy * cxy) / (n * n)
        lmin = 0.5 * tr - math.sqrt(max(0.25 * tr * tr - det, 0.0))
        s = spread * s_prev[i]
        if lmin < s * s:
            continue
        d = cxx * cyy - cxy * cxy
        # motion = mean + B (X - mean X), B = [[cux, cuy], [cvx, cvy]] C^-1
        b00 = (cux * cyy - cuy * cxy) / d
        b01 = (cuy * cxx - cux * cxy) / d
        b10 = (cvx * cyy - cvy * cxy) / d
        b11 = (cvy * cxx - cvx * cxy) / d
        lim = max_residual * s_prev[i]
        good = True
        worst = 0.0
        for q in range(k):
            j = nb[i, q]
            if near[i, q] and corr[j] >= 0:
                x = P[j, 0] - P[i, 0] - mx
                y = P[j, 1] - P[i, 1] - my
                ru = pts[corr[j], 0] - B[j, 0] - (mu + b00 * x + b01 * y)
                rv = pts[corr[j], 1] - B[j, 1] - (mv + b10 * x + b11 * y)
                if ru * ru + rv * rv > lim * lim:
                    good = False
                    break
                worst = max(worst, ru * ru + rv * rv)
        if not good:
            continue
        ok[i] = True
        res[i] = math.sqrt(worst) / s_prev[i]
        pred[i, 0] = B[i, 0] + mu - b00 * mx - b01 * my
        pred[i, 1] = B[i, 1] + mv - b10 * mx - b11 * my
        jac[i, 0] = 1.0 + b00
        jac[i, 1] = b01
        jac[i, 2] = b10
        jac[i, 3] = 1.0 + b11
    return pred, ok, jac, res
