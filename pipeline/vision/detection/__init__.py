"""Stage 3: marker detection in ONE camera view (determinant-of-Hessian blobs, bright on dark).

Markers are bright dots on a dark background. The detector works on a small Gaussian scale space
built on an image pyramid (two scales per octave, octave ``L`` computed on the image reduced
``2**L`` times, so the cost stays around a millisecond per 640x480 view whatever the largest scale):

1. scale-normalised determinant of Hessian ``DoH = sigma**4 (Lxx Lyy - Lxy**2)``, kept only where
   the Laplacian ``Lxx + Lyy`` is negative (bright blob; DoH alone is positive for both polarities);
2. non-maximum suppression in space (3x3 neighbourhood) and across scales (the strongest scale
   within ``min_separation_px`` wins);
3. sub-pixel centres: background-subtracted intensity centroid on the full-resolution image in a
   disc of radius ``centroid_radius_factor * sqrt(2) * sigma`` about the peak, iterated;
4. rejection of what is not a marker (LED-ring glare, the bright rim outside the skin): a blob must
   be brighter than its surrounding ring on ALL sides (``isolation``), must not be much larger than
   the median blob, must not be elongated, and must not sit on a saturated plateau.

The Gaussian filtering is OpenCV's; the per-pixel and per-marker loops around it (pyramid
reductions, DoH and peaks, sparse peak work, suppression, centroids and photometry, the touching-marker
screens and the pair tests) are numba-compiled
with the arithmetic of the numpy/OpenCV code they replaced (tests compare them with OpenCV where it
has the same operation).

Modules, in the order a frame goes through them:

- :mod:`.params` -- :class:`DetectionParams`, the :data:`MONOCULAR_DOME` preset, :func:`marker_radius_px`;
- :mod:`.images` -- input validation (:func:`to_grey`), the [0, 1] scale, reused per-thread buffers;
- :mod:`.pyramid` -- the half-octave area pyramid;
- :mod:`.scale_space` -- DoH maps per scale on the pyramid, and the candidates (step 1);
- :mod:`.peaks` -- spatial peaks, cross-scale maxima and suppression (step 2);
- :mod:`.candidates` -- the named columns of the candidate record passed between the steps;
- :mod:`.photometry` -- sub-pixel centroids, ring, sectors and core per candidate (step 3);
- :mod:`.rejection` -- glare, rim and debris rejection, touching markers (step 4), with
  :mod:`.crowding` (the touching-marker screens);
- :mod:`.pairs` -- two touching or overlapping pins found as one blob split back into two, with
  :mod:`.pair_profiles` (the profiles of each examined blob);
- :mod:`.numpy_order` -- numpy's float ranges, sums and median in the compiled kernels, bit for bit;
- :mod:`.detect` -- :func:`detect_markers`, the steps chained; :func:`compile_crowded_kernels`.

References
----------
StereoTacTip paper, Sec. "Marker Localization" (greyscale, Determinant of Hessian blob detection).
"""

from pipeline.vision.detection.detect import detect_markers
from pipeline.vision.detection.images import to_grey
from pipeline.vision.detection.params import MONOCULAR_DOME, DetectionParams, marker_radius_px

__all__ = ["DetectionParams", "MONOCULAR_DOME", "detect_markers", "marker_radius_px", "to_grey"]
