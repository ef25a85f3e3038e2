"""DTRC ring coding of one view (:func:`code_rings`): meshing, peeling, coding by angle and by
prediction, then the certainty rule."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.design import SensorDesign
from pipeline.types import Blobs
from pipeline.vision.dtrc.mesh import OUTLIER_NN_FACTOR, _median, _nn_and_mesh
from pipeline.vision.dtrc.peel import _peel_flat
from pipeline.vision.dtrc.prediction import _shift_by_prediction, _verify_and_grow
from pipeline.vision.dtrc.proposals import _certain_ids
from pipeline.vision.dtrc.ring_codes import (_annulus_rotation, _code_by_angles, _design_flat, _design_order,
                                             _design_radii, _design_rings, _ring_by_angle, _shift_code, _unmatched)
from pipeline.vision.identity import R_NO_BLOB, REASONS, use_triangulation


@dataclass(frozen=True)
class RingCoding:
    """Result of ring coding one view.

    Attributes
    ----------
    ids : (N,) int64
        Canonical design id of each input blob, -1 where uncoded (spurious or ambiguous).
    ring : (N,) int64
        Peel index of each blob (0 = outermost ring found), -1 for points dropped before meshing.
    ring_sizes_found : tuple of int
        Number of blobs in each peeled ring, outermost first.
    ring_sizes_expected : tuple of int
        The design's ring sizes, outermost first.
    unmatched_ids : (M,) int64
        Design ids not coded in this view.
    mesh_edges : (E, 2) int64
        Edges (blob indices) of the carved Delaunay mesh (for drawing).
    messages : tuple of str
        Human-readable notes on mismatches.
    unmatched_reasons : tuple of str
        Why each of ``unmatched_ids`` was not identified (same order).
    carried : (N,) int64
        The ids the next frame of the sequence follows on from: ``ids``, except when the markers'
        frame-to-frame motion and this frame's certainty rule disagreed widely, in which case only
        their agreement is in ``ids`` and ``carried`` is the frame-to-frame reading (neither is
        emitted alone; the next frame keeps testing one against the other).
    by_motion : (N,) bool
        Blobs whose id only the markers' motion from earlier frames gave (the frame-to-frame map or
        re-acquisition; this frame's certainty rule left them open). Such an id rests on the marker
        moving as its neighbours do, which a sharp tip dragged across the skin breaks; the stereo
        geometry is asked again about it (:mod:`pipeline.cross_view`).
    """

    ids: np.ndarray
    ring: np.ndarray
    ring_sizes_found: tuple[int, ...]
    ring_sizes_expected: tuple[int, ...]
    unmatched_ids: np.ndarray
    mesh_edges: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))
    messages: tuple[str, ...] = ()
    unmatched_reasons: tuple[str, ...] = ()
    carried: np.ndarray | None = None
    by_motion: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.carried is None:
            object.__setattr__(self, "carried", self.ids)
        if self.by_motion is None:
            object.__setattr__(self, "by_motion", np.zeros(len(self.ids), bool))

    @property
    def complete(self) -> bool:
        """True when every design marker was coded."""
        return len(self.unmatched_ids) == 0

    @property
    def coded(self) -> int:
        return int(np.sum(self.ids >= 0))


def code_rings(blobs: Blobs, design: SensorDesign, *, previous: tuple[np.ndarray, np.ndarray] | None = None,
               history=None, rest_before: bool = False) -> RingCoding:
    """DTRC ring coding of one view.

    Parameters
    ----------
    blobs : Blobs
        Marker centres of ONE view (px).
    design : SensorDesign
        Gives the ring count (``pattern.layers``), ring sizes and canonical ids.
    previous : (xy_px (M, 2), ids (M,)[, xy_px_before (K, 2), ids_before (K,)]), optional
        The identified markers of the previous frame of the same view: they propose ids
        (:func:`carry_ids`) where ring coding cannot, certified like any other proposal, and keep
        their ids where the frame-to-frame map certifies which blob each became
        (:func:`pipeline.vision.identity.frame_to_frame`; the frame before the previous one, when
        given, sets where each marker is expected at its last velocity).
    history : sequence of (xy_px (K, 2), ids (K,)[, lost (K,) bool]), optional
        The identified markers of the frames before the previous one, most recent first: a marker lost
        since is re-acquired when its neighbours' motion from its last certified position certifies a
        free blob (:func:`pipeline.vision.identity.reacquire.reacquire`). An entry with ``lost`` holds
        also markers that were not identified there, placed where their neighbours' motion carried
        them (:func:`pipeline.vision.identity.reacquire.carry_lost`): only those may be re-acquired
        from it. Used only with ``previous``.
    rest_before : bool
        ``previous``'s frame before is the rest pattern (where the calibration puts the unloaded
        markers), not a frame of the sequence: the motion from it is only a guess at the markers'
        velocity (a sequence may start pressed, a calibration is off by a pixel or two), so the
        frame-to-frame map starts from the previous positions, and predicts a marker from the fit of
        the motion's change only where that fit's worst residual is no larger than the increment's.

    Returns
    -------
    RingCoding
        Canonical id per blob (-1 uncoded), ring membership, sizes and messages. Never raises on bad
        input: an empty or unusable point set gives all markers unmatched.

    Notes
    -----
    Assumes the image is not mirrored relative to the sensor frame (true for this sensor: u grows with
    x, v with y) and rotated by less than half the pitch angle of ring 1 (30 deg for hexagon/circular,
    22.5 deg for square).
    """
    pts = np.ascontiguousarray(blobs.xy_px, dtype=np.float64)
    n = len(pts)
    xy_d, drings = _design_rings(design)
    d_ids_flat, d_ang_flat, d_off, d_gap = _design_flat(design)
    n_layers = design.pattern.layers
    expected = tuple(len(drings[k][0]) for k in range(n_layers - 1, -1, -1))
    ids = np.full(n, -1, np.int64)
    msgs: list[str] = []
    if n < 4:
        return RingCoding(ids, np.full(n, -1, np.int64), (), expected, np.arange(len(xy_d), dtype=np.int64),
                          messages=(f"only {n} blobs",), unmatched_reasons=(f"only {n} blobs detected",) * len(xy_d))
    nn, tri = _nn_and_mesh(pts)
    use_triangulation(pts, None if tri is None else tri[0])
    med_nn = _median(nn)
    active = nn <= OUTLIER_NN_FACTOR * med_nn
    n_dropped = n - int(np.count_nonzero(active))
    if n_dropped:
        msgs.append(f"dropped {n_dropped} isolated blob(s) outside the lattice")
    ring_flat, ring_off, ring_of, edges = _peel_flat(pts, active, n_layers, med_nn, tri)
    found = tuple(int(s) for s in np.diff(ring_off))
    n_leftover = n - n_dropped - len(ring_flat)
    if n_leftover:
        msgs.append(f"{n_leftover} blob(s) left inside after {n_layers} rings")

    # code from the centre outward: peel r <-> layer n_layers - 1 - r. Complete, regular rings are
    # coded by their angles in one compiled pass; it stops at a layer needing the cases below.
    failed = bool(n_leftover or n_dropped)
    layer, theta = _code_by_angles(pts, ring_flat, ring_off, 0, 0.0, ids, d_ids_flat, d_ang_flat, d_off, d_gap)
    if layer == 0 and design.pattern.kind == "circular" and found and found[0] == expected[0]:
        # no centre: the rings about it fix the rotation jointly (each alone only modulo its pitch)
        theta = _annulus_rotation(pts, active, ring_flat[:found[0]], d_ang_flat, d_off, _design_radii(design)) or 0.0
    while layer < n_layers:
        d_ids, _, d_ang = drings[layer]
        r = n_layers - 1 - layer
        members = ring_flat[ring_off[r]:ring_off[r + 1]] if r < len(found) else np.empty(0, np.intp)
        done = False
        if len(members) == len(d_ids) and layer > 0:
            # complete but irregular (a deformed skin): the cyclic order still holds; find the
            # start by prediction from the rings inside, or for the first ring (only the centre
            # is coded) by the angular fit alone; verified against the neighbours below
            members, phi = _ring_by_angle(pts, members)
            how = "prediction from the rings inside"
            shift = _shift_by_prediction(members, d_ids, pts, ids, xy_d, _design_order(design),
                                         design.pattern.separation_mm)
            shift = None if shift < 0 else int(shift)
            if shift is None and int((ids >= 0).sum()) < 4:
                s_ang, _, spread = _shift_code(phi, d_ang, theta)
                shift, how = (s_ang, "its angles") if spread < math.pi / len(d_ids) else (None, "")
            if shift is not None:
                ids[np.concatenate((members[shift:], members[:shift]))] = d_ids
                theta += float(np.angle(np.mean(np.exp(1j * (np.concatenate((phi[shift:], phi[:shift]))
                                                              - d_ang - theta)))))
                failed = True
                msgs.append(f"ring {r} (layer {layer}): irregular, coded by {how}")
                done = True
        if not done:
            failed = True
            msgs.append(f"ring {r} (layer {layer}): found {len(members)} blobs, expected {len(d_ids)}"
                        + ("" if len(members) != len(d_ids) else " (irregular)"))
        layer, theta = _code_by_angles(pts, ring_flat, ring_off, layer + 1, theta, ids, d_ids_flat, d_ang_flat,
                                       d_off, d_gap)
    if failed:
        # a defect anywhere may shift markers between peels: check every code against its coded
        # neighbours and fill the free slots by prediction (never by guessing)
        before = int((ids >= 0).sum())
        removed = _verify_and_grow(pts, ids, active, xy_d, _design_order(design), design.pattern.separation_mm,
                                   n_layers + 2)
        msgs.append(f"verification removed {removed} code(s); prediction coded "
                    f"{int((ids >= 0).sum()) - before + removed} more")
    if previous is not None:
        previous = tuple(np.asarray(a, np.float64).reshape(-1, 2) if k % 2 == 0 else np.asarray(a, np.int64)
                         for k, a in enumerate(previous[:4]))
    if history is not None:
        history = [(np.asarray(h[0], np.float64).reshape(-1, 2), np.asarray(h[1], np.int64),
                    *([np.asarray(h[2], bool)] if len(h) > 2 else [])) for h in history]
    ids, reason, followed, by_motion = _certain_ids(pts, ids, design, failed, msgs, previous, history, rest_before)
    unmatched = _unmatched(ids, len(xy_d))
    return RingCoding(ids, ring_of, found, expected, unmatched, edges, tuple(msgs),
                      tuple(REASONS.get(int(reason[i]), REASONS[R_NO_BLOB]) for i in unmatched),
                      ids if followed is None else followed, by_motion)
