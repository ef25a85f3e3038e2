"""The certainty rule of marker identification: an id is emitted only when the geometry leaves no
other reading; every other marker is unmatched, with a reason.

Ring coding (:mod:`pipeline.vision.dtrc`), a lattice registration, the previous frame and the other view
(:mod:`pipeline.cross_view`) only *propose* ids. A proposal becomes an identification through three tests, each about the sensor's geometry:

1. **Local consistency.** A marker's closed design neighbourhood (the marker and its identified
   design neighbours within 1.5 separations) must be one smooth piece of skin: every member lies
   within :data:`GATE` local separations of the position a local affine map fitted to the *others*
   predicts for it (leave-one-out). The fit needs three non-collinear neighbours; the local map
   must keep orientation (the image is not mirrored) and may stretch at most :data:`MAX_STRETCH`
   times more along one axis than along the other. A skin can bulge, shear and crowd smoothly; it
   cannot swap two neighbours, and a marker labelled as its neighbour sits a whole separation from
   its prediction. Inconsistent markers are removed until every remaining neighbourhood agrees.
2. **Anchoring.** Local consistency fixes ids only up to the lattice's own symmetries: a patch of
   correctly related markers could be shifted by a lattice vector, or (rings of a circular
   pattern) turned by one slot per ring, and still be locally perfect. Each connected patch of
   identified markers is compared with every such alternative reading of the design; an
   alternative is excluded by evidence: markers of the patch that it would push outside the design
   (they are there, consistent with their neighbours, so the design must contain them) plus markers
   whose neighbourhoods it breaks. A patch is anchored only if every alternative is excluded by at
   least :data:`ANCHOR_EVIDENCE` markers; otherwise all its ids are withdrawn ("not anchored").
   A patch that does not reach the pattern's outer ring on enough sides (e.g. the far side of an
   occlusion) is therefore left unidentified rather than guessed. Within an anchored patch of a
   hexagonal or square lattice, a piece of four or more markers joined to the rest only
   by bare edges (no identified marker neighbour of both ends) must be held in place by the rest
   too: where a crest crowds whole rows out of the detection, the piece beyond the gap reads as
   smoothly shifted towards the rest as in place, so every shift away from the rest must put
   :data:`ANCHOR_EVIDENCE` of its markers on slots the rest holds or outside the design; the
   survivors are then tested again.
3. **Rotation.** Turning the pattern by its symmetry angle (60 deg for hexagonal and circular
   patterns, 90 deg for square ones) changes nothing in the image. The in-plane rotation of each
   patch (Procrustes, image against design) must be within +-(half the symmetry angle - 7.5 deg),
   i.e. +-22.5 deg or +-37.5 deg; beyond, the patch is withdrawn ("rotation ambiguous").

Growth extends anchored patches: a free design slot predicted from three or more identified
neighbours takes the nearest blob when it lies within :data:`GROW_GATE` local separations, is at
least twice as near as the second-nearest blob (and 0.15 separations nearer), and no other free
slot claims it; new ids then pass the same three tests.

Last, a certified id is withdrawn when a **rival** blob could be its marker: where the neighbourhood
bends (a sharp press), the bend its leave-one-out residuals show displaces the slot's own pin too, so
a blob the reading leaves free (and no free slot claims) within the growth gate widened by that bend
is as good a reading of the slot (``certify._unrivalled``; once, so that no withdrawal cascades).

In a sequence (:class:`pipeline.vision.dtrc.DTRCTracker`) a fourth certification applies to the
markers certified in the previous frame of the same view: **the frame-to-frame map**
(:func:`frame_to_frame`). Where pins crowd (the crests of a narrow sine), the design-to-image map is
not locally affine and test 1 withdraws correct ids, but one frame's increment still is smooth:
a marker keeps its id when its neighbours' motion (a local affine fit, the marker excluded)
predicts it within a tight gate of exactly one blob, mutually. Where the design-to-image rule and
the frame-to-frame map disagree, neither reading is emitted there (see
:func:`pipeline.vision.dtrc.proposals._with_frame_to_frame`).

What remains possible, by construction: a blob that is not a marker but sits where a missing
marker should be (within :data:`GROW_GATE` of its slot) is indistinguishable from that marker
displaced, and takes its id (so does a pin whose neighbours show no bend while it is displaced). The identification benchmark therefore places spurious blobs at least
half a separation from the slots of missing markers (anywhere else, including next to present
markers, is allowed).

The rule's parts: :mod:`.constants` (gates, reason codes), :mod:`.lattice` (the design geometry),
:mod:`.fits` (local affine fits), :mod:`.fans` and :mod:`.consistency` (test 1), :mod:`.anchoring`
(tests 2 and 3), :mod:`.certify` (the rule, growth), :mod:`.temporal` (certification of carried ids by
the frame-to-frame map), :mod:`.seed` (a lattice registration proposal), :mod:`.neighbours` (the
frame's blob search structures).
"""


from pipeline.vision.identity.certify import certify, certify_whole, contradicted, grow
from pipeline.vision.identity.consistency import consistent
from pipeline.vision.identity.constants import (ANCHOR_EVIDENCE, GATE, GROW_GATE, MAX_STRETCH, R_ANCHOR, R_CONTRADICTED,
                                                R_NO_BLOB, R_NOT_FOLLOWED, R_ROTATION, REASONS, ROTATION_MARGIN_DEG)
from pipeline.vision.identity.lattice import Lattice, lattice_of, rotation_limit_deg
from pipeline.vision.identity.neighbours import use_triangulation
from pipeline.vision.identity.seed import register_seed
from pipeline.vision.identity.temporal import frame_to_frame

__all__ = ["GATE", "GROW_GATE", "ANCHOR_EVIDENCE", "MAX_STRETCH", "ROTATION_MARGIN_DEG", "REASONS", "R_ANCHOR",
           "R_CONTRADICTED", "R_NO_BLOB", "R_NOT_FOLLOWED", "R_ROTATION", "Lattice", "lattice_of", "consistent", "certify",
           "certify_whole", "contradicted", "frame_to_frame", "grow", "register_seed", "rotation_limit_deg",
           "use_triangulation"]
