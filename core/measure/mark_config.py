"""Every parameter of the marks detector, in one frozen dataclass (docs/marks.md, "Parameters").

Each field says what it is, in which unit, and why it has its value: a physical property of
a mark (SPEC §2: a white disk 8-25 mm across, a plate up to 3 mm thick or a sticker on the
skin), of the imaging (blur, noise, the projector's light) or of a fit's statistics. The
detector's modules read ``CONFIG``, the default instance; no numeric threshold lives in them.

Units: ``_mm`` millimetres in the world, ``_px`` camera pixels, ``_deg`` degrees, ``_rad``
radians; a bare number is a ratio (its docstring says of what) or a count.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MarkConfig:
    """The marks detector's parameters. Defaults are the values the accuracy table of
    docs/marks.md was measured with."""

    # ------------------------------------------------------------------ candidates (mark_candidates.py)
    # A white disk (albedo ~0.9) on skin (~0.45) or the table (~0.55) has a top-hat of 0.6-1.0 x
    # its surround; this lower bound leaves room for shading without admitting the smooth
    # variation of the skin's own albedo.
    min_relative_contrast: float = 0.1
    #: and the top-hat must stand this many noise SDs above zero (dark regions)
    min_contrast_sigmas: float = 8.0
    #: px: decoded points averaged before differencing for a normal (a disk is ~20 px across)
    normal_window_px: int = 7
    #: mm: the re-cuts at the marks' size are made a second time from every decoded point up to
    #: this predicted SD, past the cloud's own limit (``core/scan/reconstruct.MAX_POINT_SIGMA_MM``),
    #: with their own shading correction: a table lit and seen obliquely decodes most of its pixels
    #: at 0.5-2 mm, and without them neither its irradiance nor a disk on it is known. Averaged into
    #: normals these points are no worse; the fits still rest on the cloud's points
    hypothesis_max_point_sd_mm: float = 2.0
    #: candidate searches at radii this factor apart span a size range (one opening wide enough for
    #: the largest disk swallows a leg as narrow as three disks)
    scale_step: float = 1.6
    #: mm: depths further apart than this within ``depth_step_reach_px`` are an outline (the table
    #: behind the leg lies 100 mm and more further), not a surface seen obliquely (a face at 73°
    #: recedes ~2 mm per pixel)
    depth_step_mm: float = 20.0
    depth_step_reach_px: int = 3
    #: a blob cut at a depth step must have one along at least this share of its outline
    depth_step_min_border: float = 0.1
    #: the first cut, at this fraction of the seed's contrast, finds the blob's own level; a thick
    #: plate seen at a grazing angle has a side wall several times brighter than its face, and a
    #: cut this high keeps the face's level, not the wall's
    first_cut: float = 0.35
    #: the blob's wider alternative (face and lit wall together), fitted only where the first
    #: cut is refused
    wider_first_cut: float = 0.2
    #: x the blob's area: a wider cut that adds less than this is the same blob
    wider_min_growth: float = 1.3

    # ------------------------------------------------------------------ edges (mark_edges.py)
    #: px: sample spacing along a radial edge profile
    profile_step_px: float = 0.2
    #: px: the refined plane uses pixels at least this far inside the image of the top face
    top_margin_px: float = 2.0
    #: px: the outside level is the darkest sample within this of the edge (a thin shadow)
    edge_outside_px: float = 2.5
    #: mm: a side wall h tall shifts the outline by h |a_c|; edge points shifted more are dropped
    wall_shift_max_mm: float = 0.03
    #: px: a projector-shadow sliver wider than this beside the rim biases the edge inwards ...
    sliver_max_px: float = 0.0
    #: px: ... unless it is resolved, several pixels wide
    sliver_resolved_px: float = 3.0
    #: x the plate's level: a surface brighter than this beside the rim makes no clear fall
    sliver_level_max: float = 0.8
    #: clean edges needed to measure the blur; else ``default_blur_px``
    min_blur_edges: int = 5
    #: px: the optics' blur SD assumed where it cannot be measured on the rim
    default_blur_px: float = 0.8
    #: x the disk's level: a profile leaves the disk's plateau below this
    leave_plateau: float = 0.85
    #: x the disk's level: the surface just past a clear edge is at most this bright
    surface_step_level: float = 0.8
    #: share of a disk's samples at the clip level for its level to count as clipped (fewer: noise)
    clipped_solid: float = 0.9
    #: x the mark's SD: a clipped rim that raises it this much or more makes the mark "overexposed"
    clip_sd_rise: float = 1.1
    #: x the contrast: a clipped plateau's own noise
    plateau_drop: float = 0.03
    #: x the clipped contrast: the fall's lower reference crossing
    low_fraction: float = 0.1
    #: for a blurred step clipped at half its contrast or more, the half-way crossing of the clipped
    #: level lies outside the true one by at most this x its distance to the ``low_fraction``
    #: crossing: -Φ⁻¹(f/2) / (Φ⁻¹(f/2) - Φ⁻¹(f/10)) for f = 0.5
    max_bias_per_fall: float = 0.69

    # ------------------------------------------------------------------ one disk's fit (mark_fit.py)
    #: mm: a face standing less than this over the surface round it is a sticker (no side wall, no
    #: shadow sliver); plates are 1-3 mm thick (SPEC §2) and a sticker's step measures 0.0 ± 0.1 mm
    sticker_max_step_mm: float = 0.5
    #: x π r_px²: a blob's area, from a grazing view (cos ~0.15) to face-on plus a side wall
    area_range: tuple[float, float] = (0.12, 1.8)
    #: blob area / area of its fitted ellipse: an ellipse's image
    min_fill: float = 0.80
    max_fill: float = 1.15
    min_solidity: float = 0.88
    #: px: ... or, where lower, 1 − this / the ellipse's semi-minor axis in px: a rasterised
    #: ellipse's convex hull bridges its outline's pixel steps (ellipses of semi-minor axis
    #: 2.5-12 px at random sub-pixel offsets and angles: solidity down to 1 − 0.45-0.5 px / b; a
    #: disk seen at 79°, 4 px half-wide, measured 0.86). The margin allows for noise on the outline
    raster_solidity_px: float = 0.6
    #: mm: a free radius this far from the marks' size is another object (3 SD of the fit where
    #: larger, up to ``max_radius_tolerance_mm``: a straight edge's SD is huge)
    radius_tolerance_mm: float = 1.5
    max_radius_tolerance_mm: float = 3.0
    #: mm: the first plane, on the blob's interior, still holds rim and side wall
    max_plane_rms_mm: float = 0.6
    #: mm: the plane refitted to the top face alone is flat to the decoding noise; a fit locked
    #: onto side wall and shadow edge scatters 0.3-0.5 mm
    max_top_face_rms_mm: float = 0.2
    #: ... raised to this many times the face points' median predicted SD where they are noisier
    #: (a wrong model leaves 1.8-4.2 times their SD)
    face_rms_per_sigma: float = 1.5
    #: mm: edge points about the fitted circle, at most (a rim is sharp to the edge noise)
    max_circle_rms_mm: float = 0.35
    #: mm: the free radius's SD; a real rim's arc measures it to 0.01-0.3 mm, a short arc of
    #: something else (a lit patch of skin) to ~1.4 mm
    max_radius_sd_mm: float = 0.6
    #: SDs of the free radius and the size, in quadrature: a free radius further than this from
    #: the marks' size may not be the disk's rim (a short arc on a side wall or in blur); the fit is
    #: doubtful (``Mark.doubtful``): its score counts at least this disagreement (``fit_score``)
    max_radius_z: float = 4.0
    #: mm, and share of the size: a last-chance fit (a wider cut, a predicted outline) must measure
    #: its free radius at least this well (the larger of the two) to be clearly a disk
    wider_max_radius_sd_mm: float = 0.3
    wider_max_radius_sd_rel: float = 0.04
    #: decoded points for a plane (3 are always coplanar; 6 leave a tilt to measure)
    min_interior_points: int = 6
    #: deg: a disk lit more obliquely gets under cos 85° = 9 % of the light, too little to
    #: place its rim
    max_light_deg: float = 85.0
    #: rad: a plane's tilt SD about the long axis of its points, (point SD) / (spread · √n);
    #: above this its points lie on a line, not a face
    max_plane_tilt_sd_rad: float = 0.1
    #: edge points for a circle
    min_edge_points: int = 8
    #: share of a blob's border left undecoded, at most, for a sticker: a sticker lies on the skin,
    #: lit as the skin round it, so that skin is decoded; a bright patch seen between depth steps
    #: is not (0.9-1.0). A plate's surround may be shadowed all round.
    sticker_max_border_undecoded: float = 0.8
    #: share of the ring round a plate that must be decoded for the surface's normal to steady the
    #: plate's: a ring with a gap (a shadow) extrapolates on a curved surface
    surface_ring_min_decoded: float = 0.9
    #: of the image ellipse: the first plane's pixels, clear of most of the rim
    interior_fraction: float = 0.55
    #: at most this many alternations of plane (from the top face) and circle (in that plane) ...
    plane_passes: int = 6
    #: mm: ... until the centre moves less than this
    plane_converged_mm: float = 0.005
    #: triples tried for the first plane's largest consensus among the interior points
    consensus_trials: int = 150
    #: re-find the shadow-sliver edges with the centre found, refit; this many times
    sliver_passes: int = 2
    #: mm: SD of the marks' radius where it is given (a cut disk is true to ~0.1 mm in diameter);
    #: the prior steadies a short arc's centre
    radius_prior_sd_mm: float = 0.05
    #: mm: lower bound of the edge-point scatter used for weights and SDs
    edge_noise_floor_mm: float = 0.03
    #: mm: added in quadrature to every centre's SD: the RMS centre error with a true calibration
    #: (decoding biases near the disk, which a fit's own scatter does not show)
    sd_floor_mm: float = 0.05
    #: px: the half-contrast edge's systematic offset from the true rim, common to one rim, at a
    #: face-on view; it grows as 1/cos(view) ...
    edge_level_sd_px: float = 0.1
    #: ... up to this grazing a view (cos 78°)
    cos_view_min: float = 0.2
    #: a plate refitted on edges profiled across its found face counts only where those edges
    #: scatter at most this x the first edges' RMS (more: the profiles crossed something else)
    reprofile_max_rms_ratio: float = 1.25
    #: a stray arc in a plate's outline (a straight shadow edge): the rim is the circle at least
    #: this share of the edges lie on ...
    stray_arc_min_share: float = 0.6
    #: mm and px: ... within the larger of these (good rims scatter 0.03-0.1 mm) ...
    stray_arc_tol_mm: float = 0.15
    stray_arc_tol_px: float = 0.3
    #: ... found among this many triples of edges (a fixed sample: the same capture, the same marks)
    stray_arc_trials: int = 200
    #: x the radius: a sticker's centres from the shading-corrected and the lit image's edges lie
    #: at most this far apart, where it is lit within ``lit_shift_max_light_deg`` (beyond, the lit
    #: image's own edges drift with the shading); further, the two images do not see one disk
    lit_shift_max_radii: float = 0.75
    lit_shift_max_light_deg: float = 75.0
    #: a disk's face is one surface: of the decoded points within ``face_span_fraction`` of its
    #: outline, at most ``face_off_share`` lie off its plane by more than the larger of
    #: ``face_off_mm`` and ``face_off_radii`` x its radius (a sticker's sag on the leg is under a
    #: fifth of its radius); more is an outline through it (a table's edge over the floor)
    face_span_fraction: float = 0.7
    face_off_share: float = 0.1
    face_off_mm: float = 3.0
    face_off_radii: float = 0.3
    #: deg: a face lit within this gets at least cos 50° = 64 % of the light all across, so its
    #: blob covers the whole disk; a blob of less than ``min_seen_share`` of the disk's image is
    #: partly in a cast shadow or hidden, and its visible rim is in part the shadow's edge
    seen_max_light_deg: float = 50.0
    min_seen_share: float = 0.5
    #: share of a plate's top-face pixels (``top_face_pixels`` of its fit) that decode, at least:
    #: its plane is fitted to them, and a face mostly undecoded is in a shadow or lit too
    #: obliquely for its stripes; the few points that decode lie where the stripes blur into the
    #: dark, off the face (a face 14 % decoded, its points 1 mm off: its plane tilted 6°)
    min_face_decoded_share: float = 0.5

    # ------------------------------------------------------------------ sticker surface (marks_surface.py)
    #: decoded points for the local quadric (6 parameters)
    min_surface_points: int = 12
    #: the face's points for the step: within this fraction of the blob's ellipse ...
    step_face_fraction: float = 0.55
    #: ... the surface's: in this ring (x the ellipse), clear of rim and shadow
    step_ring: tuple[float, float] = (1.35, 1.9)
    #: deg: a sticker's edge point seen more obliquely than this is on the limb
    max_edge_view_deg: float = 80.0
    #: x the blob's ellipse: the decoded points a sticker's quadric is fitted to
    surface_reach: float = 1.25
    #: deg: added to the surface's slope SD before it is combined with a plate's own normal: a plate
    #: rests on its rim, not in the quadric's tangent plane
    surface_normal_floor_deg: float = 0.5

    # ------------------------------------------------------------------ labels (mark_labels.py)
    #: deg: the three table marks' normals agree within this
    table_normal_spread_deg: float = 8.0
    #: deg: the second-best table triple must be this much worse
    ambiguity_margin_deg: float = 10.0
    #: mm: with fewer than four leg marks, knee and ankle groups lie this far apart in z
    partial_leg_gap_mm: float = 100.0
    #: a pair's two marks lie about one level of the leg: their spread along it, over the
    #: knee-to-ankle distance, is at most this (hand-stuck pairs: 0.05-0.15 of the shank)
    pair_max_spread: float = 0.2
    #: deg: front and lateral normals must be this far apart round the leg to be told apart
    side_margin_deg: float = 20.0
    #: deg: with both pairs labelled, each mark faces round the leg nearer its own role's mark of the
    #: other pair, or not more than this worse (a tibia twists 20-30° between knee and ankle)
    cross_pair_margin_deg: float = 20.0
    #: deg: without the other pair, front marks face ~90° round the leg (0 = lateral), lateral
    #: ones 0-40°; this splits them
    lone_split_deg: float = 65.0
    #: mm: with one leg pair lost, the other is the knee's if it is this far over the table top
    #: (ankle marks sit 50-100 mm over the sole, knee marks 300-500 mm)
    knee_min_height_mm: float = 200.0
    #: leg marks face sideways: |n_z| below this (the leg stands; z is up, SPEC §1)
    leg_normal_max_z: float = 0.7

    # ------------------------------------------------------------------ the search (marks.py)
    #: mm: radii searched where the size is not given: SPEC §2's 8-25 mm diameters with a margin
    #: (a disk seen at a grazing angle, or blurred, measures a little off)
    size_range_mm: tuple[float, float] = (3.5, 13.5)
    #: free radii within this fraction of each other (or 3 SD) are one size
    size_cluster_rel: float = 0.08
    #: mm: a given radius this far (or 3 SD) from the measured one fits no mark
    given_size_tolerance_mm: float = 0.75
    #: mm: a doubtful mark (free radius far from the size) is kept only with edges this clean
    #: (good rims: 0.05-0.2 mm)
    doubtful_max_edge_rms_mm: float = 0.25
    #: of the first pass's fits: the capture's kind of mark (a clinic sticks one kind), the only
    #: one fitted where a disk's step is unclear
    common_kind_share: float = 0.75
    #: of the two predicted outlines of one blob (the disk alone, the plate's face and wall
    #: together), the plate's is kept where it rests on this many times the disk's edge points (it
    #: reaches the far rim the disk alone, cut over the wall, misses); else the disk's
    shape_plate_edge_ratio: float = 1.5
    #: share of a second-look blob that must be decoded: a sparsely decoded far surface's
    #: corrected image is a patchwork whose bits can pass for a disk
    second_look_min_decoded: float = 0.8
    #: share of a second-look blob's border left undecoded, at most: along the edge of the
    #: reconstruction the normal (over 7 x 7 points) is wrong and the corrected image a streak
    second_look_max_border_undecoded: float = 1 / 3
    #: ½ SD²: the score of a fit that matches the model exactly, against no mark there
    #: (``mark_selection.fit_score``): above the worst fit that passes its checks (edges and face
    #: at their 3-SD limits and a doubtful radius: ½ (3² + 3² + 4²) = 17), so every such fit is worth
    #: keeping where nothing better overlaps it
    fit_score_base: float = 20.0
    #: ½ SD²: the prior odds against a hypothesis, by how it was made (``HypothesisSource.tier``):
    #: the first search's blobs, the re-cuts at the marks' size, the outlines derived from a blob
    #: no cut fits (each finds more that are not a mark's image than the one before). A re-cut's
    #: fit must fit ~2.4 SD better, a derived one ~3.5 SD better, to outweigh a first-search fit;
    #: and a choice whose fits all score within this of the base needs no hypothesis of that tier
    #: (``mark_selection.settled``)
    source_penalty: tuple[float, float, float] = (0.0, 3.0, 6.0)
    #: x the marks' radius: two fits whose centres lie closer are two views of one disk (two disks'
    #: centres lie two radii apart or more; two fits of one disk within a fraction of a radius)
    overlap_radii: float = 1.0
    #: x the marks' radius: a blob's decoded points this near a fitted mark's centre are that
    #: disk's (its face, rim and side wall, with the blur)
    explained_radii: float = 1.15
    #: a re-cut of which less than this share is left unexplained by the fitted disks is another
    #: view of them; with more left, the rest is a hypothesis of its own (two disks cut as one)
    unexplained_min_share: float = 0.25
    #: px: the rest's bands narrower than twice this (the fitted disk's blurred border, its halo
    #: in the shading-corrected image) are cut off before its largest part is taken (``unexplained``)
    unexplained_opening_px: int = 2
    #: the best non-overlapping fits among which the seven the labels accept are chosen
    #: exhaustively (C(10, 7) = 120 labellings)
    selection_pool: int = 10
    #: mm: a clicked disk may be fitted on edges that scatter this much (the click says a disk
    #: is there, and the fit's SD carries the scatter)
    snap_max_edge_rms_mm: float = 0.7

    # ---- a sticker fitted to its image (``mark_image_model``)
    #: x the radius: the pixels fitted reach this far from the centre (the disk and a ring of its
    #: surround, for the surround's level) ...
    image_fit_reach: float = 1.3
    #: px: ... and this far beyond, for the blur
    image_fit_margin_px: int = 3
    #: x the radius: the surface under the disk is fitted to the decoded points this far from its
    #: centre: more points for its height at the centre (a steep view carries it along the ray
    #: ~5-fold at 80°), but not so far that a quadric bends over an edge nearby (a table's front
    #: edge 2 radii from a sticker's centre tilted its surface 1.5° and moved it 0.5 mm)
    image_fit_surface_reach: float = 1.5
    #: decoded points there at least: fewer (a table seen at 80° under strong ambient light decodes
    #: a dozen) leave the surface's height at the centre to a fit of six terms on a few points
    image_fit_min_surface_points: int = 40
    #: a pixel whose decoded point lies off the surface fitted by more than this many times its RMS,
    #: and this many mm, sees another surface (an outline, the table's front face): not fitted
    image_fit_off_surface_sd: float = 4.0
    image_fit_off_surface_mm: float = 1.0
    #: an undecoded pixel is fitted only where its light is at least this share of the decoded
    #: surface's round it (else it is a shadow, or beyond a silhouette)
    image_fit_min_lit_share: float = 0.5
    #: x the fitted blur (px): nor within this far of such a pixel or of one that sees another
    #: surface (the blur spreads their light onto the surface's pixels beside them)
    image_fit_guard_blurs: float = 3.0
    #: mm: the image fit's radius error from its model (a blur that is not Gaussian, the camera's
    #: tone curve: 0.01-0.14 mm on whole disks), in quadrature with its SD where a radius is
    #: checked against the marks' size
    image_fit_radius_sd_mm: float = 0.075
    #: samples per pixel side on which the disk is drawn before it is blurred, at most (odd: the
    #: middle one is the pixel's centre, where the blurred image is read) ...
    image_fit_subsamples: int = 3
    #: px: ... as few as move the rim by at most this where its image curves most (``_subsamples``:
    #: a 6.5 mm disk at 2.5 px/mm read 0.4 % small at 70° drawn once per pixel, 0.2 % thrice)
    image_fit_max_tip_shift_px: float = 0.05
    #: px: the blur's SD the fit starts from, and the range it may take
    image_fit_blur_start_px: float = 1.0
    image_fit_blur_range_px: tuple[float, float] = (0.3, 4.0)
    #: x the image noise: residuals beyond are weighted down (Huber), a neighbour or an outline in the window
    image_fit_huber: float = 2.5
    #: Levenberg-Marquardt iterations, at most
    image_fit_iterations: int = 40
    #: the image fit's residuals over the image noise, less one, at most: a disk's image matches
    #: the model to within the noise (a blur that is not Gaussian, a rim's shading: 0-0.2); beyond,
    #: the window holds what is not a flush disk
    image_fit_max_excess: float = 0.5
    #: SDs: a disk's contrast over its surround at least (no disk is there otherwise)
    image_fit_min_contrast_z: float = 5.0
    #: points of a neighbouring disk's rim projected to outline its image (its polygon's chords
    #: fall inside the ellipse by up to r (1 - cos(π / n)): 0.02 px on a disk 17 px in radius)
    image_fit_neighbour_rim_points: int = 64
    #: a plate on the table plates' plane (``mark_plate_image``): rounds of its face's height
    #: from its own decoded points, ...
    plate_image_height_rounds: int = 3
    #: mm: ... until the height and the centre move less than this, ...
    plate_image_height_tol_mm: float = 0.01
    #: ... counting the pixels whose blurred light is at least this share the face's, ...
    plate_image_face_share: float = 0.99
    #: ... where at least this many decode (else the plane's height alone). Its thickness is
    #: fitted (the wall's height sets where the face's rim is read), up to this many times the capture's
    plate_image_min_face_points: int = 10
    plate_image_max_thickness_ratio: float = 3.0
    #: deg: the SD of one plate's face normal, where the table's plane is that one plate's (the
    #: face's own height is then corrected by its decoded points, above; the tilt shapes the ellipse)
    plate_image_one_plate_tilt_deg: float = 0.5
    #: radii of the mark's: where no table plate is found, the table's plane is that of the
    #: decoded points between these distances of a plate's blob (inside: the plate, its wall and
    #: its shadow, which at 78° light reaches 4.7 thicknesses past the rim)
    plate_image_surround_radii: tuple[float, float] = (2.0, 4.0)
    #: points: the table's plane through every decoded point on it is fitted to at most this
    #: many, evenly thinned (its consensus tries each of CONFIG.consensus_trials planes on each)
    table_plane_max_points: int = 20000
    #: share of the capture's thickness a plate so fitted on the table's plane may differ by (the
    #: capture's is read where the leg plates meet the skin, which curves away: 5 % low seen)
    plate_image_thickness_tolerance: float = 0.25
    #: a plate so fitted is one of the kit's: its face's light at least this share of what the
    #: found plates' one albedo gives there by Lambert's law (their faces' light over the
    #: projector's irradiance: the cosine of its incidence over the distance squared)
    plate_image_min_light_share: float = 0.5
    #: share of the face's light the model's light may be off by (Lambert's law per plate, not per
    #: point; the table lit linearly), in quadrature with the noise's allowance
    plate_image_model_error: float = 0.03
    #: px: the same model's error in where it places the plate's image (a blur that is not one
    #: Gaussian beside a wall on one side only), in its covariance
    plate_image_model_error_px: float = 0.1
    #: px: the surround round a plate (``mark_surround``) is measured from decoded points at least
    #: this far outside its face, base and shadow: a point within a blur's reach of the plate's
    #: edges mixes their light and reads a depth between the two (on a flat table, 3 px clear
    #: of a plate read it curved away 80-100 mm round; the same cut out read it flat)
    surround_quadric_clear_px: float = 3.0
    #: radii: the ring the surround is measured in reaches this far past that, and so do the
    #: pixels its image fit reads (past it the quadric is not measured, and other surfaces enter)
    surround_quadric_radii: float = 0.6
    #: and is measured where at least this share of that ring's pixels decode (a table seen near
    #: grazing decodes a handful of points round a plate, which a quadric fits to any surface)
    surround_quadric_min_decoded: float = 0.5
    #: the surround's tilt and curvature are drawn where they differ from none by these χ² over
    #: their own covariance (1 % at their 2 and 3 degrees of freedom)
    surround_quadric_chi2: tuple[float, float] = (9.21, 11.34)

    # ---- every chosen plate placed again by its image on its face's plane (``mark_plate_refit``)
    #: radii: how far the image fit's centre may move from the rim fit's (its window and reach)
    plate_refit_reach: float = 0.5
    #: sample rays per pixel per axis in that fit (the step above takes CONFIG.image_fit_subsamples:
    #: it starts radii away; from a rim fit's start 2 × 2 place the centre within 0.02 mm of 3 × 3)
    plate_refit_subsamples: int = 2
    #: of the kit's radius: the bounds of a fitted face's radius
    plate_refit_radius_range: tuple[float, float] = (0.8, 1.25)

    # ---- a plate's side wall (``mark_wall``)
    #: blurs (SD as read from the image, the pixel's width in it): the wall points fitted are
    #: imaged at least this far from the wall's top and bottom (nearer, the pixel also sees the
    #: face or the surface in front, and the point is pulled in or out: 0.25-0.3 mm with a
    #: 2.4-2.7 px wall at 1 px blur and only 1 px margin)
    wall_margin_blurs: float = 1.25
    #: degrees: only the wall facing the camera, within this of its direction in the face's plane
    #: (towards the silhouette the camera sees the wall edge-on, its pixels mixed with what is
    #: beyond)
    wall_arc_deg: float = 50.0
    #: mm: a wall point lies this near the cylinder of the plate's radius round the rim fit's
    #: axis (the rim fit's centre at a grazing view: within ~0.6 mm)
    wall_window_mm: float = 1.0
    #: wall points at least (half of them in each half of the band)
    wall_min_points: int = 12
    #: Gauss-Newton iterations of the wall's circle, and its Huber threshold in robust SDs
    wall_iterations: int = 8
    wall_huber_k: float = 1.5


CONFIG = MarkConfig()
