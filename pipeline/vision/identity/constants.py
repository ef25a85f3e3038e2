"""Gates and limits of the certainty rule (:mod:`pipeline.vision.identity`), in local marker
separations unless stated, and the reason codes of unidentified markers."""


#: Leave-one-out gate, in local separations. A correct marker's prediction error is its own centre
#: error plus the fit's (detector noise ~0.01, jitter tested up to 0.3); a marker carrying its
#: neighbour's id is ~1 separation off.
GATE = 0.35
#: Growth gate, in local separations: a blob farther than this from a free slot's prediction is not
#: taken (a neighbouring marker is >= 0.7 separations away even with 0.3 separations of jitter).
GROW_GATE = 0.4
#: A blob takes (or keeps) an id only if it is at least twice as near to the slot's prediction as
#: any other blob and this many local separations nearer.
AMBIGUITY_MARGIN = 0.15
#: A free blob (one no identified marker claims) within :data:`GROW_GATE` of a slot's prediction is
#: where growth would take the slot's marker to be, displaced. The ratio test
#: (:data:`AMBIGUITY_MARGIN`) still gives the slot to a nearer labelled blob, on the premise that a
#: correct marker sits where its neighbourhood puts it: within the scatter of the neighbourhood's own
#: leave-one-out residuals, and within this many local separations of its prediction (a marker with a
#: free blob within the growth gate sat <= 0.07 separations from its prediction in 600 views with up
#: to 10 % missing and spurious blobs, and in 600 pressed views with 5 %). A labelled blob farther off
#: than both this and :data:`STANDS_OUT` times the largest residual of its immediate neighbours is
#: displaced from a neighbourhood that is otherwise affine, and the free blob is as good a reading:
#: at the tip of a 5 mm press of a sigma 1 mm Gaussian the deepest pin shows 0.36 separations off
#: its six neighbours' affine prediction in the oblique view (parallax of its 4 mm extra depth; the
#: neighbours' residuals 0.05), and a spurious blob 0.15 separations from the prediction took its id.
SETTLED = 0.075
#: See :data:`SETTLED`: twice the largest leave-one-out residual of the immediate neighbours.
STANDS_OUT = 2.0
#: ... and, the other way round, a free blob within this many times that largest residual of the
#: prediction (and within :data:`GROW_GATE`) is as good a reading of the slot as a labelled blob
#: sitting on the prediction: the bend that shows in the neighbours' residuals displaces the slot's
#: own pin more, the deepest pin of a sharp press most. At the tip of a 5 mm press of a sigma 1.46 mm
#: Gaussian (square121) the deepest pin stood 0.28-0.30 separations off its neighbours' affine
#: prediction, up to 4.3 times their largest residual, while a spurious blob within 0.04 of the
#: prediction took its id. Larger factors reach the residuals that detector jitter alone leaves
#: (8 cost 1.3 points of coverage with 10 % missing and spurious blobs; 5 cost 0.2).
#: The same bend widens the window in which a free blob rivals the labelled one, beyond the growth gate
#: by the largest residual (and no farther than this many times it), once the reading is certified
#: (``certify._unrivalled``): near a sharp tip the slot's own pin stood 0.45-0.46 separations off the
#: prediction (its neighbours' residuals up to 0.20-0.29) while a spurious blob 0.09-0.12 off took its id.
DISPLACED_REACH = 5.0
#: A marker with two or more unidentified design neighbours (its prediction is extrapolated across
#: the gap) is ambiguous when another blob lies within this many local separations of it: a spurious
#: blob 0.2-0.3 separations from such a marker in a strongly pressed view was nearer the
#: extrapolated prediction than the marker itself.
CLOSE_BLOB = 0.4
#: A prediction extrapolated across a wide gap (two or more immediate design neighbours unidentified)
#: errs more the farther the slot lies from the centroid of its identified immediate neighbours
#: (0 for a closed neighbourhood, 2/3 of a separation with three consecutive of six, 0.87 with two):
#: a free blob competes for the slot within :data:`GROW_GATE` plus this many separations per
#: separation of that offset. Near the tip of a sharp press (hexagon217_sep180, 5 mm, sigma 1.1-2.2 mm)
#: the real marker of a slot predicted from its outer side only stood 0.41-0.48 separations off the
#: prediction, beyond the growth gate, while its inner neighbour's pin (or a spurious blob) stood
#: within 0.21 and took the id; 0.1 withdraws those five views. It applies only to slots with a design
#: fan (hexagonal and square patterns), whose intact fans still check the reading once competed slots
#: are withdrawn: applied to a circular pattern (no fans), one pressed circular217_dome stereo trial
#: of the full identification benchmark was read shifted by a marker (149 wrong ids), as withdrawing
#: its competed slots left the shifted reading certified; without the reach that trial has none.
EXTRAPOLATION_REACH = 0.1
#: Markers of evidence needed to exclude an alternative reading of a patch.
ANCHOR_EVIDENCE = 2
#: Largest ratio of the two singular values of a local affine map. Pins crowding on a steep flank
#: exceed 1.6 (a twin terrain tap on hexagon217 lost 27 of 217 ids at 1.6); a patch whose ids jump
#: by one slot across a seam fits as a shear of about one separation per row (ratio ~2-3).
MAX_STRETCH = 2.0
#: Margin kept from half the pattern's symmetry angle.
ROTATION_MARGIN_DEG = 7.5
#: Radius (design separations) of a slot's immediate design neighbours: a hexagonal lattice's first
#: shell (1) and a square lattice's diagonals (1.41), not the second shell (1.73 hexagonal, 2 square).
IMMEDIATE_PITCHES = 1.5
#: Radius (design separations) of the neighbourhood a local affine map is fitted to: two shells,
#: so that a slot on the convex edge of an identified patch (two immediate neighbours) still has a
#: fit, while the map stays local (a press changes the skin's local scale over several separations).
NEIGHBOURHOOD_PITCHES = 2.1
#: A circular pattern's first three rings must each fit an affine image of the design ring to within
#: this fraction of ring 1's radius (measured: <= 0.17 under a 5 mm off-centre press through the
#: nominal cameras; a reading centred on a marker of ring 1 leaves >= 0.31 on ring 2, 0.39 on ring 3).
RING_ROUND = 0.22
#: ... and their centres must agree to within this fraction of ring 1's radius (a reading centred
#: on a marker of ring 1 is a whole radius off).
RING_CENTRE = 0.3
#: Radius (design separations) about its anchor slot within which a similarity placement proposes
#: ids (growth takes over beyond: a press bulges the pattern by up to ~15 % of its radius).
SEED_RADIUS = 3.5
#: Identified immediate neighbours (within 1.5 separations) a marker needs.
MIN_IMMEDIATE = 2
#: ... and to count as evidence against an alternative reading that would put it outside the design.
#: A spurious blob just outside the pattern, which a reading shifted by one row takes for an outer-
#: ring marker, has only the two true outer-ring markers beside it; the markers of a pattern's outer
#: ring have three or four.
EVIDENCE_IMMEDIATE = 3
#: With this many identified immediate neighbours a marker's neighbourhood fit uses only them (the
#: second shell is used where fewer are identified: at the edge of a patch or of a gap).
LOCAL_ONLY = 5
#: A patch is withdrawn when unidentified blobs sit where the lattice would continue one step
#: beyond the design's outer ring (hexagonal, square) beside this many consecutive outer-ring slots:
#: a reading shifted by one row leaves the pattern's real outer row there (a side of 7-9 blobs in a
#: row); spurious blobs land there scattered.
BEYOND_HITS = 5
#: Largest ratio of the singular values of the affine map a closed fan's neighbours may show when
#: the fan is intact (:func:`_embedded`): its topology, not the map's shape, rules out seams and
#: swaps there, so only a fold-free crowding limit is kept (measured up to 1.9 at the tip of a 5 mm
#: press of the sharpest twin Gaussian on the 0.5 mm skin).
FAN_MAX_STRETCH = 3.0
#: A slot has a closed fan only if its design neighbours leave no angular gap wider than this about
#: it (hexagonal 60, square 45 deg inside the pattern; an outer-ring slot leaves >= 180 deg).
FAN_MAX_GAP_DEG = 135.0
#: A fan's neighbours are degenerate (no affine map through them) when the determinant of their
#: design scatter is below this x pitch^4 (a rounding-level floor: a real fan's is ~pitch^4).
FAN_DEGENERATE = 1e-12
#: Nearest blobs examined for the emptiness of a fan (a hexagonal fan has 6 vertices).
FAN_QUERY = 24
#: The centre test of a circular pattern needs, in each of its first three rings, the blobs of at
#: least this fraction of the ring's slots ...
RING_COVERAGE = 2.0 / 3.0
#: ... and at least this many (an affine fit to fewer says nothing about roundness).
RING_MIN_MARKERS = 4
#: A reading that passes the centre test is withdrawn when the same blobs read with the centre on a
#: marker of ring 1 (each slot moved by that marker's offset) fit rings 1-3 this many times better
#: (largest per-ring affine residual, :func:`~pipeline.vision.identity.centring._ring_residual`), the
#: moved reading's rings holding at least RING_ALT_COVERAGE of their slots (fewer: not compared).
#: Measured 2026-11-27 on 796 circular217 readings that reach the test (single views pressed 5 mm by
#: Gaussians of sigma 1-5 mm up to 6 mm off the axis, 0-10 % missing and spurious blobs): correct
#: readings at most 1.50 times the best moved reading (99 % below 1.10); the one reading centred on a
#: marker of ring 1 (158 wrong ids) 12.6 times.
RING_ALT_RATIO = 3.0
RING_ALT_COVERAGE = 1.0 / 3.0
#: ... and the three rings' affine maps proportional to within this fraction (a press changes each
#: ring's radius; a camera's perspective is common to all three).
RING_SHAPE = 0.25
#: A circular pattern read without its centre rings is centred by three consecutive rings further out,
#: each holding at least this fraction of its slots ...
ANNULUS_COVERAGE = 2.0 / 3.0
#: ... whose affine maps turn by no more than this fraction of what turning every ring by one slot adds
#: (a reading so turned then shows at least 1 - ANNULUS_TWIST of it). Measured 2026-11-29 on the true readings
#: of 3,097 circular217 views without their centre rings (``python -m benchmarks.identity_search --draws 4000
#: --seed 29 --sigma 1.5 6 --off 3 --rate 0.05 --lateral 0.5 --hidden 0.05 0.25``: pressed 5 mm, 5-25 % of the
#: markers hidden about a point near the centre, up to 5 % missing and spurious blobs): at most 0.36, 99 %
#: below 0.23, 5 of them beyond this bound (refused: no id rather than a doubtful one).
ANNULUS_TWIST = 1.0 / 3.0
#: Design scale (mm) passed to the ring fits in place of the pitch: it switches the collinearity
#: limit of the fits off (a ring is never collinear), so only too few points make a fit unusable.
RING_FIT_NO_COLLINEARITY_MM = 1e-9
#: Design-lattice construction (fractions of the design separation): a rotation or shift maps a slot
#: onto a slot when it lands within SLOT_MATCH_SYMMETRY (symmetry test, exact up to rounding) or
#: SLOT_MATCH_SHIFT (alternative readings); a lattice step is a centre neighbour within LATTICE_STEP;
#: a site beyond the outer ring is one with no slot within BEYOND_EMPTY.
SLOT_MATCH_SYMMETRY = 0.1
SLOT_MATCH_SHIFT = 0.25
LATTICE_STEP = 1.1
BEYOND_EMPTY = 0.5
#: A piece of a patch joined to the rest only by bare edges (no identified marker neighbour of both
#: ends) may have been read shifted across the gap only by a shift that makes every such edge longer
#: than this many separations: the rows between were crowded out of the detection (a crest of a
#: narrow sine pressed 4 mm crowded three separations into 1.3 spacings, and two rows vanished).
SEAM_LONGER = 1.5
#: Smallest patch that is reported (a patch needs neighbourhoods of three to be tested at all).
MIN_PATCH = 4

# per-slot reason codes (0 = identified)
R_OK, R_NO_BLOB, R_AMBIGUOUS, R_INCONSISTENT, R_FEW, R_ANCHOR, R_ROTATION, R_CONTRADICTED, R_NOT_FOLLOWED = range(9)
#: internal status: the test needs a blob search (run only for the blobs whose test needs one)
_NEED_SEARCH = 99
REASONS = {
    R_NO_BLOB: "no blob at its predicted position",
    R_AMBIGUOUS: "two blobs near its predicted position",
    R_INCONSISTENT: "inconsistent with its identified neighbours",
    R_FEW: "fewer than three identified neighbours",
    R_ANCHOR: "in a patch that could be shifted along the lattice (not anchored)",
    R_ROTATION: "pattern rotation beyond the unambiguous range",
    R_CONTRADICTED: "two certified readings disagree (this frame's coding and the previous frame's ids)",
    R_NOT_FOLLOWED: "carried id not confirmed by the frame-to-frame map",
}
