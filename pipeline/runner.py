"""The per-frame runner: detect -> match (DTRC) -> triangulate -> refraction -> skin surface.

:class:`Reconstructor` chains the stage functions for one sensor and keeps the little state the
stages need across frames (the tracker, the undeformed reference for the linear refraction model).
:func:`pipeline.batch.reconstruct` runs it over a frame source and writes the results to a folder.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.design import SensorDesign
from pipeline.cross_view import across_views
from pipeline.places import carry
from pipeline.errors import UserError
from pipeline.geometry.refraction import RefractionError, correct_exact, correct_linear, project_through_stack
from pipeline.geometry.surface import MIN_MARKERS, height_map, skin_surface
from pipeline.view_process import RightView
from pipeline.threads import VIEW_THREADS, ViewPolicy, both_views, default_view_threads, one_thread
from pipeline.geometry.triangulation import matched_rays, triangulate
from pipeline.types import Blobs, HeightMap, MarkerCloud, MarkerMatches, SkinSurface, StereoCalibration, StereoFrame

__all__ = ["Reconstructor", "FrameResult", "RunnerError", "REFRACTION_MODES", "TRACKERS"]

REFRACTION_MODES = ("exact", "linear")
TRACKERS = ("dtrc", "nn")
#: Stereo check: a left/right pair is one marker only if its two rays, refracted through the stack,
#: pass within this distance (mm) of each other. Correct pairs: <= 0.01 mm on twin frames (pixel
#: noise); two different markers: mostly 0.2-6 mm (measured on a crowded 217-marker terrain tap).
STEREO_GATE_MM = 0.15
#: ... and the triangulated marker lies in the gel: between the gel/acrylic interface and this far
#: (mm) beyond its rest depth (the skin bulges outward only slightly beside an indentation).
STEREO_BULGE_MM = 1.0
#: A first frame read from the rest pattern (see :class:`pipeline.vision.dtrc.DTRCTracker`) keeps no pair when the
#: stereo check rejects more than this fraction (a right calibration's rest pattern leaves none on the twin's frames).
REST_DOUBT = 0.1


class RunnerError(UserError, ValueError):
    """Bad runner options (unknown refraction mode or tracker, missing reference)."""


@dataclass(frozen=True)
class FrameResult:
    """Everything the runner produced for one frame.

    ``matches`` pixels per marker; ``apparent`` straight-ray positions; ``corrected`` refraction-corrected
    marker positions; ``skin`` skin points + normals (None with fewer than MIN_MARKERS markers);
    ``height_map`` (None unless requested); ``timings_ms`` per stage and ``total``; ``unmatched_ids``
    design ids not reconstructed in this frame; ``n_expected`` markers of the design;
    ``unmatched_reasons`` {id: why it was not reconstructed} (per view: the certainty rule's reason,
    see :mod:`pipeline.vision.identity`; or the stereo check's). 3-D in the sensor frame, mm.
    """

    index: int
    timestamp_s: float
    matches: MarkerMatches
    apparent: MarkerCloud
    corrected: MarkerCloud
    skin: SkinSurface | None
    height_map: HeightMap | None
    timings_ms: dict[str, float]
    unmatched_ids: np.ndarray
    n_expected: int
    n_blobs: tuple[int, int] = (0, 0)
    notes: tuple[str, ...] = field(default_factory=tuple)
    unmatched_reasons: dict = field(default_factory=dict)

    @property
    def n_matched(self) -> int:
        return len(self.corrected)

    def max_abs_dz_mm(self, design: SensorDesign) -> float:
        """Largest |z - z_rest| over the corrected markers; NaN for a frame without markers (there is
        no measurement, which is not the same as an undeformed skin)."""
        if len(self.corrected) == 0:
            return float("nan")
        rest = design.rest_markers_mm()[self.corrected.ids, 2]
        return float(np.max(np.abs(self.corrected.xyz_mm[:, 2] - rest)))

    def summary(self, design: SensorDesign) -> str:
        if self.n_matched == 0:
            dz = "NO MARKERS reconstructed, no depth measured"
        else:
            dz = f"max |dz| {self.max_abs_dz_mm(design):.3f} mm"
        s = f"frame {self.index}: {self.n_matched}/{self.n_expected} markers, {dz}, {self.timings_ms['total']:.1f} ms"
        if len(self.unmatched_ids):
            ids = ",".join(str(i) for i in self.unmatched_ids[:12]) + ("..." if len(self.unmatched_ids) > 12 else "")
            s += f", unmatched ids {ids}"
            why = self.reason_counts()
            if why:
                s += " [" + "; ".join(f"{n} {r}" for r, n in why.items()) + "]"
        if self.notes:
            s += " (" + "; ".join(self.notes) + ")"
        return s

    def reason_counts(self) -> dict[str, int]:
        """How many unmatched ids each kind of reason accounts for (view prefixes and the stereo
        check's numbers dropped), most frequent first."""
        from collections import Counter

        kinds = Counter()
        for r in self.unmatched_reasons.values():
            first = r.split("; ")[0]
            kind = first.split(": ", 1)[1] if first.startswith(("left: ", "right: ")) else first
            kinds["stereo check" if kind.startswith("stereo check") else kind] += 1
        return dict(kinds.most_common())


def _rest_px(design: SensorDesign, calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the calibration puts every marker of the undeformed skin in each view (px): the rest
    pattern DTRC falls back on to anchor a first frame's reading (:class:`pipeline.vision.dtrc.DTRCTracker`);
    None when the markers cannot be projected."""
    try:
        left, right = project_through_stack(design.rest_markers_mm(), calib, design)
    except RefractionError:
        return None
    return (left, right) if np.all(np.isfinite(left)) and np.all(np.isfinite(right)) else None


def _empty_cloud() -> MarkerCloud:
    return MarkerCloud(np.empty(0, np.int64), np.empty((0, 3)))


class Reconstructor:
    """Reconstruct markers and skin for one sensor, frame by frame.

    Parameters
    ----------
    design : SensorDesign
    calib : StereoCalibration
    refraction : {"exact", "linear"}
        Exact ray tracing through the stack, or the paper's linear model relative to a reference frame.
    n_gel : float, optional
        Refractive index: for "linear" the effective index (the paper fits 1.51); for "exact" it
        overrides the design's gel index. Default: ``design.optics.gel_n``.
    tracker : {"dtrc", "nn"}
        DTRC identification in every frame, or nearest-neighbour tracking from the first frame.
    reference : StereoFrame or MarkerCloud, optional
        Undeformed frame (or its apparent cloud) for the linear model; default: the first processed frame.
    detection_params : DetectionParams, optional
        Fixed detection parameters. Default: the full scale space for the first frame that shows at
        least half the design's markers in both views, then the scale space narrowed to the marker
        radius measured on it (:meth:`DetectionParams.for_marker_radius`; ~40 % less detection time,
        accuracy unchanged: tests/test_detection.py).
    with_height_map : bool
        Also resample the skin on a grid (``height_map_step_mm``) each frame.
    view_threads : {1, 2}, optional
        2: the right view is detected and identified on a worker thread while the calling thread does the
        left (:func:`pipeline.threads.both_views`; identical results); 1: both on the calling thread.
        Default: 2 where the process may use two or more CPUs.
    view_process : bool, optional
        The right view in a worker process (:mod:`pipeline.view_process`: for views with defects; DTRC only).
    """

    def __init__(self, design: SensorDesign, calib: StereoCalibration, *, refraction: str = "exact",
                 n_gel: float | None = None, tracker: str = "dtrc", reference: StereoFrame | MarkerCloud | None = None,
                 detection_params=None, with_height_map: bool = False, height_map_step_mm: float = 0.25,
                 view_threads: int | None = None, view_process: bool = False) -> None:
        if refraction not in REFRACTION_MODES:
            raise RunnerError(f"refraction mode {refraction!r}: choose one of {REFRACTION_MODES}")
        if tracker not in TRACKERS:
            raise RunnerError(f"tracker {tracker!r}: choose one of {TRACKERS}")
        if n_gel is not None and not 1.0 <= n_gel <= 3.0:
            raise RunnerError(f"n_gel {n_gel}: refractive index outside [1, 3]")
        if view_threads is not None and view_threads not in VIEW_THREADS:
            raise RunnerError(f"view threads {view_threads!r}: choose one of {VIEW_THREADS}")
        self.view_threads = default_view_threads() if view_threads is None else int(view_threads)
        self._views = ViewPolicy(self.view_threads)
        from pipeline.vision import detection, dtrc

        calib.check_fits_frame()
        self.design, self.calib = design, calib
        self.refraction, self.tracker_name = refraction, tracker
        self.n_gel = n_gel
        self._detect = detection.detect_markers
        self._detection_params = detection_params if detection_params is not None else detection.DetectionParams()
        self._narrow = detection_params is None       # narrow the scales once the marker size is known
        self._match_stereo = dtrc.match_stereo
        rest = _rest_px(design, calib)
        self._tracker = (dtrc.DTRCTracker(design, rest=rest) if tracker == "dtrc"
                         else dtrc.NearestNeighbourTracker(design))
        self._right = RightView(design, rest) if view_process and tracker == "dtrc" else None   # a worker process
        self.with_height_map, self.height_map_step_mm = with_height_map, height_map_step_mm
        self._all_ids = np.arange(design.marker_count, dtype=np.int64)
        self._rest_z = design.rest_markers_mm()[:, 2]
        self._reference: MarkerCloud | None = None
        self._stereo_reasons: dict[int, str] = {}
        self._last_places = None      # the previous frame's markers in space (places.Places)
        if isinstance(reference, MarkerCloud):
            self._reference = reference
        elif isinstance(reference, StereoFrame):
            matches = self._match(reference)[0]
            self._reference = triangulate(matches, calib)
        elif reference is not None:
            raise RunnerError("reference must be a StereoFrame or a MarkerCloud")

    @property
    def reference(self) -> MarkerCloud | None:
        """Apparent cloud of the undeformed reference frame (linear model), once known."""
        return self._reference

    def _stereo_check(self, matches: MarkerMatches) -> tuple[MarkerMatches, np.ndarray, MarkerCloud, tuple]:
        """Drop pairs that cannot be one marker: refracted rays more than :data:`STEREO_GATE_MM` apart,
        or a 3-D point outside the gel (closer than the acrylic, or more than :data:`STEREO_BULGE_MM`
        beyond the rest marker depth). Catches identity errors that differ between the two views
        (e.g. a ring coded with different shifts). Returns the kept matches, the rejected ids, the
        exactly refraction-corrected cloud of the kept matches (with the runner's index in exact mode,
        the design's otherwise) and their viewing rays (:func:`matched_rays`): the check has to trace
        the rays anyway, and each marker's rays are traced independently, so the cloud IS
        ``correct_exact`` of the kept matches."""
        rays = matched_rays(matches, self.calib)
        if len(matches) == 0:
            return matches, np.empty(0, np.int64), _empty_cloud(), rays
        cloud, gap, ok = self._one_marker(matches, rays)
        z = cloud.xyz_mm[:, 2]
        self._stereo_reasons = {
            int(i): (f"stereo check: the two views' rays miss by {g:.2f} mm (gate {STEREO_GATE_MM} mm)"
                     if g > STEREO_GATE_MM else f"stereo check: triangulated depth z = {zz:.2f} mm is outside the gel")
            for i, g, zz in zip(cloud.ids[~ok].tolist(), gap[~ok].tolist(), z[~ok].tolist())}
        if getattr(self._tracker, "read_from_rest", False) and np.count_nonzero(~ok) > REST_DOUBT * len(ok):
            # a view read from the rest pattern trusts the calibration to place the markers: views
            # that disagree this often say it does not (a rest pattern off by a whole separation
            # reads every marker as its neighbour), so none of the frame's pairs is kept
            why = (f"stereo check: read from the rest pattern, the views disagree on {np.count_nonzero(~ok)} of "
                   f"{len(ok)} pairs: the calibration does not place the markers where they are")
            self._stereo_reasons = {int(i): why for i in cloud.ids.tolist()}
            ok[:] = False
        if ok.all() and len(cloud.ids) == len(matches.ids):      # every pair kept: the cloud has one point per pair
            return matches, np.empty(0, np.int64), cloud, rays
        kept_cloud = cloud if ok.all() else MarkerCloud(cloud.ids[ok], cloud.xyz_mm[ok])
        good = np.isin(matches.ids, kept_cloud.ids)
        if good.all():
            return matches, np.empty(0, np.int64), kept_cloud, rays
        rejected = matches.ids[~good]
        kept = MarkerMatches(matches.ids[good], matches.left_px[good], matches.right_px[good],
                             np.union1d(matches.unmatched_ids, rejected))
        return kept, rejected, kept_cloud, tuple(r[good] for r in rays)

    def _one_marker(self, matches: MarkerMatches, rays: tuple | None = None,
                    rest_z: np.ndarray | None = None) -> tuple[MarkerCloud, np.ndarray, np.ndarray]:
        """The stereo check's test of each pair: (the exactly corrected cloud, its rays' gaps, whether each
        of its pairs can be one marker: rays within :data:`STEREO_GATE_MM`, the point in the gel, i.e.
        beyond the acrylic and at most :data:`STEREO_BULGE_MM` beyond ``rest_z`` indexed by the pair's id;
        by default the design's rest depth of the marker)."""
        cloud, gap = correct_exact(matches, self.calib, self.design, n_gel=self.n_gel if self.refraction == "exact"
                                   else None, return_gap=True, rays=rays)
        z = cloud.xyz_mm[:, 2]
        rest_z = self._rest_z if rest_z is None else rest_z
        ok = (gap <= STEREO_GATE_MM) & (z >= self.design.gel_acrylic_z_mm) & (z <= rest_z[cloud.ids] + STEREO_BULGE_MM)
        return cloud, gap, ok

    def _locate(self, left_px: np.ndarray, right_px: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per candidate pair (pixel in each view, marker id proposed): can it be one marker (:meth:`_one_marker`),
        and its 3-D point (mm; NaN where the rays do not reach the gel)."""
        pairs = MarkerMatches(np.arange(len(ids), dtype=np.int64), np.asarray(left_px, np.float64).reshape(-1, 2),
                              np.asarray(right_px, np.float64).reshape(-1, 2), np.empty(0, np.int64))
        cloud, _, ok = self._one_marker(pairs, rest_z=self._rest_z[ids])
        out, xyz = np.zeros(len(ids), bool), np.full((len(ids), 3), np.nan)
        out[cloud.ids], xyz[cloud.ids] = ok, cloud.xyz_mm
        return out, xyz

    def _commit(self, left: Blobs, right: Blobs, codings=None) -> MarkerMatches:
        """The tracker's pairs of the frame: each view's coding (``codings`` from :meth:`_view`, or coded
        here) completed from the other's through the stereo geometry (:func:`pipeline.cross_view.across_views`),
        then committed (what the next frame follows on from includes the completion)."""
        if not hasattr(self._tracker, "code_view"):
            return self._tracker.update(left, right)
        if codings is None:
            codings = (self._tracker.code_view(0, left), self._tracker.code_view(1, right))
        completed = across_views((left, right), codings, self.design, self._locate, self._last_places)
        matches = self._tracker.commit(left, right, completed)
        if self._right is not None:       # the worker's tracker follows this one's
            self._right.repeat("advance", self._tracker.certified)
        return matches

    @property
    def view_process_error(self) -> str | None:
        """Why the view worker process was stopped (the right view then coded here), or None."""
        return self._right and self._right.error

    def _checked(self, matches: MarkerMatches) -> tuple[MarkerMatches, np.ndarray, MarkerCloud, tuple]:
        """:meth:`_stereo_check`, and the rejected ids not carried into the next frame as certain."""
        out = self._stereo_check(matches)
        if len(out[1]) and hasattr(self._tracker, "forget"):
            self._tracker.forget(out[1])
            if self._right is not None:
                self._right.repeat("forget", out[1])      # the worker's tracker too
        self._last_places = carry(self._last_places, out[2], self.design)
        return out

    def identify(self, left: Blobs, right: Blobs) -> MarkerMatches:
        """The identification stages of :meth:`process` on one frame's detected blobs: the tracker
        (with what earlier frames left it) and the stereo check. The pairs kept; for benchmarks that
        draw blobs directly (defects placed where a detector could not be made to put them)."""
        return self._checked(self._commit(left, right))[0]

    def _view(self, view: int, image: np.ndarray) -> tuple[Blobs, object, float, float]:
        """Detect one view's markers and, with a tracker that codes views apart, identify them (reads only
        earlier frames' state: the two views run at once, :func:`pipeline.threads.both_views`)."""
        t0 = time.perf_counter()
        blobs = self._detect(image, params=self._detection_params)
        t1 = time.perf_counter()
        coding = self._tracker.code_view(view, blobs) if hasattr(self._tracker, "code_view") else None
        return blobs, coding, t1 - t0, time.perf_counter() - t1

    def _match(self, frame: StereoFrame) -> tuple[MarkerMatches, tuple[int, int], dict[str, float]]:
        t0 = time.perf_counter()
        if self._right is not None:
            (left, lc, ld, lm), (right, rc, rd, rm) = self._right.both(self._view, frame.left, frame.right,
                                                                       self._detection_params)
            waited = []
        else:
            threads, waited = self._views.next(), []
            (left, lc, ld, lm), (right, rc, rd, rm) = both_views(self._view, frame.left, frame.right,
                                                                 threads=threads, waited=waited)
        t1 = time.perf_counter()
        if waited:
            self._views.record(ld + lm, waited[0])
        matches = self._commit(left, right, (lc, rc) if lc is not None else None)
        t2 = time.perf_counter()
        if self._narrow and min(len(left), len(right)) >= self.design.marker_count // 2:
            from pipeline.vision.detection import marker_radius_px

            both = Blobs(np.vstack([left.xy_px, right.xy_px]), np.concatenate([left.sigma_px, right.sigma_px]),
                         np.concatenate([left.response, right.response]))
            self._detection_params = self._detection_params.for_marker_radius(marker_radius_px(both))
            self._narrow = False
        # "detect" and "match" are each view's work added up, wherever it ran; "views" is the wall time
        # of both views' detection and identification (less than their sum when they overlap)
        return matches, (len(left), len(right)), {"detect": 1e3 * (ld + rd), "match": 1e3 * (lm + rm + t2 - t1),
                                                  "views": 1e3 * (t1 - t0)}

    def close(self) -> None:
        """Stop the view worker process, if any (also done when the runner is dropped); the runner stays usable."""
        if self._right is not None:
            self._right.close()

    def process(self, frame: StereoFrame) -> FrameResult:
        """Run all stages on one frame. A frame without enough markers gives an empty result (all ids
        unmatched) rather than an error; bad frames are rejected by :class:`StereoFrame` itself."""
        if not isinstance(frame, StereoFrame):
            raise RunnerError(f"Reconstructor.process: expected a StereoFrame, got {type(frame).__name__}")
        t_start = time.perf_counter()
        with one_thread():  # BLAS, OpenMP and OpenCV at one thread for the frame (pipeline.threads)
            res = self._process(frame)
        res.timings_ms["total"] = 1e3 * (time.perf_counter() - t_start)   # the whole call, limits and result included
        return res

    def _process(self, frame: StereoFrame) -> FrameResult:
        notes: list[str] = []
        matches, n_blobs, timings = self._match(frame)
        t = time.perf_counter()
        matches, rejected, exact_cloud, rays = self._checked(matches)
        timings["stereo_check"] = 1e3 * (time.perf_counter() - t)
        reasons = self._view_reasons()
        for i in rejected.tolist():
            reasons[int(i)] = self._stereo_reasons.get(int(i), "stereo check: not one marker in both views")
        if len(rejected):
            notes.append(f"stereo check rejected {len(rejected)} left/right pair(s) (ids "
                         + ",".join(map(str, rejected[:12])) + ("..." if len(rejected) > 12 else "") + ")")
        t = time.perf_counter()
        apparent = triangulate(matches, self.calib, rays=rays)
        timings["triangulate"] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        if self.refraction == "exact":
            corrected = exact_cloud
        else:
            if self._reference is None:
                if len(apparent) < self.design.marker_count:
                    notes.append(f"reference frame has {len(apparent)}/{self.design.marker_count} markers")
                self._reference = apparent
            n = self.n_gel if self.n_gel is not None else self.design.optics.gel_n
            corrected = correct_linear(apparent, self._reference, n, self.design)
        timings["refraction"] = 1e3 * (time.perf_counter() - t)
        t = time.perf_counter()
        skin = None
        if len(corrected) >= MIN_MARKERS:
            skin = skin_surface(corrected, self.design)
        elif len(corrected):
            notes.append(f"only {len(corrected)} markers: no skin surface")
        timings["surface"] = 1e3 * (time.perf_counter() - t)
        hm = None
        if self.with_height_map and skin is not None:
            t = time.perf_counter()
            hm = height_map(skin, step_mm=self.height_map_step_mm, mask_radius_mm=self.design.gel.radius_mm)
            timings["height_map"] = 1e3 * (time.perf_counter() - t)
        unmatched = np.delete(self._all_ids, corrected.ids)   # the design's ids not reconstructed, in order
        if n_blobs[0] == 0 or n_blobs[1] == 0:
            notes.append(f"no markers detected ({n_blobs[0]} left, {n_blobs[1]} right blobs)")
        why = {int(i): reasons.get(int(i), "not identified in both views") for i in unmatched.tolist()}
        return FrameResult(index=frame.index, timestamp_s=frame.timestamp_s, matches=matches, apparent=apparent,
                           corrected=corrected, skin=skin, height_map=hm, timings_ms=timings,
                           unmatched_ids=unmatched, n_expected=self.design.marker_count, n_blobs=n_blobs,
                           notes=tuple(notes), unmatched_reasons=why)

    def _view_reasons(self) -> dict[int, str]:
        """{id: reason} for ids the tracker left unidentified in either view (the DTRC tracker's
        certainty-rule reasons; the nearest-neighbour tracker gives none)."""
        out: dict[int, str] = {}
        codings = getattr(self._tracker, "last_codings", None)
        if not codings:
            return out
        for side, coding in zip(("left", "right"), codings):
            for i, r in zip(coding.unmatched_ids.tolist(), coding.unmatched_reasons):
                out[int(i)] = (out[int(i)] + "; " if int(i) in out else "") + f"{side}: {r}"
        return out
