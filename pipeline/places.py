"""The markers' places in space from frame to frame: where a marker's design neighbours' motion puts it, and the
runner's previous frame in space, with the markers it did not pair carried on.

A marker's previous 3-D point moved by the mean motion of its design neighbours placed in both frames predicts
its point now (:func:`moved_with_neighbours`): on the twin's narrow-sine presses from rest within 0.12-0.21
separations at every frame, where the design's affine map errs by up to 0.85 at 5 mm. That holds where the
neighbours moved alike (:func:`moved_alike`, :data:`MOTION_SPREAD`); a tip dragged across the skin moves the
neighbours on its two sides apart, and the marker under it with neither. A view drops a marker for a frame (a glare
spot, a spurious blob merged with it): its place is carried by its neighbours' motion for :data:`CARRY_FRAMES`
frames (:func:`carry`), so that it is still predicted by its motion when it is seen again.
:mod:`pipeline.cross_view` takes pairs on this evidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.design import SensorDesign
from pipeline.vision.identity import lattice_of

__all__ = ["CARRY_FRAMES", "MOTION_SPREAD", "Places", "carry", "moved_alike", "moved_with_neighbours",
           "neighbour_sets"]

#: A marker's neighbours moved alike when each moved within this many separations of their mean motion: then that
#: motion places the marker. An id that only the markers' motion gave, with another free blob near it whose rays meet
#: the other view's marker too, is settled by its motion in space only then (``pipeline.cross_view._motion_settled``).
#: A tip dragged across the skin moves the neighbours on its two sides apart and the marker under it with neither:
#: the sequence search's wrong pair (hexagon217_sep180, a sigma 1.3 mm tip slid 2 mm a frame) had its neighbours'
#: motions up to 0.50 separations from their mean, its point 1.6 separations from their mean motion's prediction
#: (the tip dropped it 2.8 mm in that frame); on the twin's narrow-sine press sequences (square121, pi/5, 3 % + 3 %
#: defects) the same decisions saw at most 0.30, and over the sequence search's 205 on hexagon217_sep180 and
#: square121 (seed 5000) those kept by the motion at most 0.397, none wrong.
MOTION_SPREAD = 0.4
#: Frames a marker's place in space is carried by its neighbours' motion after its last checked pair
#: (:func:`carry`), as a view's lost markers are carried for re-acquisition
#: (:data:`~pipeline.vision.identity.reacquire.REACQUIRE_FRAMES`).
CARRY_FRAMES = 2


def neighbour_sets(i: int, lat, *placed: np.ndarray):
    """Marker ``i``'s design neighbours that have a point in every one of ``placed`` ((N, 3), NaN where not), at
    least three of them: its immediate neighbours, then those within 2.5 pitches."""
    for table in (lat.nbr, lat.nbr2):
        nb = table[i][table[i] >= 0]
        for space in placed:
            nb = nb[np.isfinite(space[nb, 0])]
        if len(nb) >= 3:
            yield nb


def moved_with_neighbours(i: int, place: np.ndarray, lat, now: np.ndarray, then: np.ndarray,
                          spread: float | None = None) -> np.ndarray | None:
    """Marker ``i``'s ``place`` in the frame before moved by the mean motion of its design neighbours placed in both
    frames (``then`` -> ``now``, (N, 3), NaN where not; three at least, :func:`neighbour_sets`); None where too few,
    or, with ``spread`` (separations), where one of them moved farther than that from their mean motion."""
    nb = next(neighbour_sets(i, lat, now, then), None)
    if nb is None:
        return None
    motion = now[nb] - then[nb]
    mean = motion.mean(axis=0)
    if spread is not None and np.linalg.norm(motion - mean, axis=1).max() > spread * lat.pitch:
        return None
    return place + mean


def moved_alike(i: int, before: tuple, lat, space: np.ndarray) -> np.ndarray | None:
    """Marker ``i``'s previous point (``before[0]``) moved by the mean motion of its design neighbours placed in both
    frames (``before[1]`` -> ``space``) where they moved alike: each within :data:`MOTION_SPREAD` separations of
    their mean motion (:func:`moved_with_neighbours`); None otherwise (or with fewer than three of them)."""
    return moved_with_neighbours(i, before[0][i], lat, space, before[1], MOTION_SPREAD)


@dataclass(frozen=True)
class Places:
    """Markers in space after a frame, for the next frame's predictions by motion: ``ids`` (N,), ``xyz_mm``
    (N, 3) and ``age`` (N,): 0 for the frame's checked pairs, k for a place carried k frames since the marker's
    last checked pair (:func:`carry`)."""

    ids: np.ndarray
    xyz_mm: np.ndarray
    age: np.ndarray


def carry(previous: Places | None, cloud, design: SensorDesign) -> Places:
    """The frame's checked pairs ``cloud`` (``.ids``, ``.xyz_mm``) as :class:`Places`, with the markers ``previous``
    placed and the frame did not pair carried on (:data:`CARRY_FRAMES`): each moved by the mean motion of its design
    neighbours that are checked pairs in both (three at least: immediate neighbours, else those within 2.5
    pitches). A view drops a marker for a frame (a glare spot, a spurious blob merged with it), and without a
    place the next frame has only the design's affine map of its neighbours to propose it with, which a crest
    that crowds the pins bends by most of a separation."""
    ids = np.asarray(cloud.ids, np.int64)
    xyz = np.asarray(cloud.xyz_mm, np.float64)
    age = np.zeros(len(ids), np.int64)
    if previous is None or len(previous.ids) == 0 or len(ids) == 0:
        return Places(ids, xyz, age)
    paired = np.zeros(max(int(ids.max()), int(previous.ids.max())) + 1, bool)
    paired[ids] = True
    go = ~paired[previous.ids] & (previous.age < CARRY_FRAMES)
    if not go.any():                        # every marker placed before is paired again (a clean frame)
        return Places(ids, xyz, age)
    lat = lattice_of(design)
    n = len(lat.xy)
    now, then = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    now[ids] = xyz
    measured = previous.age == 0
    then[previous.ids[measured]] = previous.xyz_mm[measured]
    add_ids, add_xyz, add_age = [], [], []
    for i, p, a in zip(previous.ids[go].tolist(), previous.xyz_mm[go], previous.age[go].tolist()):
        q = moved_with_neighbours(i, p, lat, now, then)
        if q is not None:
            add_ids.append(i)
            add_xyz.append(q)
            add_age.append(a + 1)
    if not add_ids:
        return Places(ids, xyz, age)
    return Places(np.r_[ids, add_ids], np.vstack([xyz, add_xyz]), np.r_[age, add_age])
