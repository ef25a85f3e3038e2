"""Stage 4: Delaunay-Triangulation-Ring-Coding (DTRC) marker matching and tracking.

Per view (paper Sec. "Marker Localization", Alg. 1, Table III):

1. **Meshing** — Delaunay triangulation of the blob centres (compiled, certified; Qhull otherwise), after
   dropping isolated points far outside the lattice (nearest neighbour > ``OUTLIER_NN_FACTOR`` x the
   median). The mesh is carved from the outside: boundary triangles that are slivers (circumradius
   > ``SLIVER_RADIUS_FACTOR`` x their shortest edge, i.e. hull edges bridging a concavity) or that have
   a boundary edge longer than ``LONG_EDGE_FACTOR`` x the median edge are removed until none is left,
   so the boundary follows the marker lattice. A triangle that spans the gap of ONE missing marker
   (circumradius = pitch, shortest edge = pitch) survives, so a missing marker does not pull an inner
   marker into the outer ring.
2. **Ring extraction** — the edge ring is the set of vertices on boundary edges (edges of exactly one
   remaining triangle; interior markers have ``links`` reciprocal links, edge markers fewer), ordered
   counter-clockwise by ``atan2(v, u)`` about the centroid of the remaining points. The ring is
   peeled (its triangles removed) and the next ring extracted, ``layers`` times (Table III's ``m``).
3. **Coding** — rings are coded from the centre outward. A ring whose size equals the design's and
   whose spacing is regular is rotated onto the design ring: the cyclic shift minimising the angular
   residual against the design angles plus the rotation carried from the ring inside it (ring 1 fixes
   the rotation, unambiguous within +-half its pitch, i.e. +-30 deg for hexagons). This gives the
   canonical ids of :mod:`pipeline.design` on an undeformed sensor and is consistent between views and
   over time. A ring whose size or spacing disagrees is coded by prediction instead: each design slot
   is predicted from a local affine fit to its already-coded design neighbours and takes the blob that
   is the mutual nearest within ``PREDICT_GATE`` pitches; slots without such a blob are *unmatched*
   (reported, never guessed).

Tracking: identity is the code, so :class:`DTRCTracker` re-codes every frame (large, fast motions
keep identity); markers certified in the previous frame also keep their ids where the frame-to-frame
map certifies them (pins crowding beyond what the design-to-image rule can read). :class:`NearestNeighbourTracker` is the paper's KNN baseline.

Speed: with ~100-300 blobs per view, per-call overheads dominate, so the per-frame path (triangulation,
nearest neighbours, carving and peeling, angular coding, pairing) runs as a few numba-compiled kernels
(~0.3 ms per stereo frame for 127 markers); the numpy classes they replace remain the definitions
(:class:`_Mesh`). The defect paths of strongly pressed frames (irregular rings coded by prediction,
verification and growth) are compiled too: the local affine fits take their neighbours from a port of
scipy's cKDTree that reproduces its choice among equidistant lattice points, so the codes are those of

Modules, in the order of the stage: :mod:`.mesh` (step 1), :mod:`.peel` (step 2), :mod:`.ring_codes`
(step 3 by angle), :mod:`.prediction` (step 3 by prediction), :mod:`.proposals` (the certainty rule
over the proposals), :mod:`.coding` (one view), :mod:`.tracking` (stereo pairs and frames).
"""


from pipeline.vision.dtrc.coding import RingCoding, code_rings
from pipeline.vision.dtrc.mesh import LONG_EDGE_FACTOR, OUTLIER_NN_FACTOR, SLIVER_RADIUS_FACTOR, mesh_edges
from pipeline.vision.dtrc.peel import peel_rings
from pipeline.vision.dtrc.prediction import PREDICT_GATE
from pipeline.vision.dtrc.proposals import carry_ids
from pipeline.vision.dtrc.tracking import DTRCTracker, NearestNeighbourTracker, match_stereo, read_from_rest

__all__ = ["RingCoding", "code_rings", "carry_ids", "match_stereo", "DTRCTracker", "NearestNeighbourTracker", "read_from_rest",
           "mesh_edges", "peel_rings", "OUTLIER_NN_FACTOR", "SLIVER_RADIUS_FACTOR", "LONG_EDGE_FACTOR", "PREDICT_GATE"]
