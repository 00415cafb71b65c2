"""Options of the ``ssf`` frontend (``ssf:`` in the run config), one section per stage.

The frontend is a chain of stages (``flowslam.frontends.ssf``)::

    network -> pose_start -> refine (static refinement) -> flow_to_pose -> recovery -> objects

``network`` always runs; ``refine.enabled: false`` keeps the network's flow as it is
(then ``pose_start`` is not needed, and neither ``recovery`` nor ``objects`` can run:
they check the step and verify objects against the refined ego motion);
``objects.enabled: false`` gives the static points the rigid flow of the measurement
and keeps the network's flow for the rest. The ``flow_to_pose`` stage uses the run's
``flow_odometry:`` section. ``recovery`` checks every step for a motion fault and
re-initialises a faulty one globally (``docs/motion_recovery.md``).

Metres, seconds, radians except fields whose name says ``_deg``.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from flowslam.config.base import StrictModel


class NetworkStageConfig(StrictModel):
    """The learned scene-flow network: per-point flow and dynamic probability of scan k-1."""

    weights: Path | None = None
    """Weights file; None = the weights shipped in the package (hash-checked)."""
    max_points: int = Field(16384, ge=16)
    """Points sampled per scan for the network (flow is propagated to all points)."""
    dynamic_threshold: float = Field(0.3, gt=0, lt=1)
    """A point is a dynamic candidate when sigmoid(logit) exceeds this (the objects stage
    verifies candidates, so recall matters more than precision: 0.3 beat 0.5 on the
    held-out simulated sequences used for tuning)."""
    device: str = "auto"
    """torch device of the network: 'auto' (the GPU when torch sees CUDA, else the CPU),
    'cpu', 'cuda', 'cuda:1', ..."""
    cuda_bf16: bool = False
    """On a CUDA device, run the forward pass under bf16 autocast (the selective scan stays
    float32). Ignored on the CPU. Off by default: see ``docs/sceneflow_evaluation.md``
    (GPU section) for its measured speed and flow difference."""
    grid_half_extent_m: float | None = Field(None, gt=0)
    """Opt-in speed option: run the network on the square of this half-width (m) around the
    sensor instead of the grid its weights were trained on (None: that grid, +-51.2 m for
    the shipped weights). It must take whole cells of the U-Net's coarsest level off each
    side (12.8 m for the shipped weights: 38.4 or 25.6 m), so that every level's cells stay
    where they were; positions keep the trained scale and the decoder its scan order. The
    U-Net's work falls with the area (38.4 m: 56 %); points beyond are static candidates
    with the constant-velocity prior's flow (the static refinement registers them as
    before; only the geometric movers find moving objects there). Measured at 38.4 m
    (docs/sceneflow_evaluation.md, issue 12, stop 46): KITTI 0-15 end to end 3.09 -> 3.47
    frames/s, network 138 -> 109 ms, objects 142 -> 113 ms, RPE(1) 1.20 cm both; the real
    AV2 pair 3-way EPE 0.053 -> 0.047 m; but fresh simulated `dt` Dynamic IoU -0.014 /
    -0.017 and instance recall -0.03 (the network sees less context near the edge of the
    square), fresh `rush-hour` AccStrict 90.1 -> 88.6 %: not the default."""
    num_threads: int | None = Field(None, ge=1)
    """torch intra-op threads on the CPU. None: 1 when ``OMP_WAIT_POLICY=PASSIVE`` (the
    CLI's default; a second thread gains nothing there, measured) or with ``ssf.lookahead``
    (the other core runs the rest of the frame), else torch's default
    (``flowslam.sceneflow.network.model.default_cpu_threads``)."""
    trim_heap_every: int = Field(25, ge=0)
    """On the CPU the stage tunes glibc to keep freed blocks for reuse (faster); every this
    many scans it hands the heap's free pages back to the OS (``malloc_trim``), so that the
    resident set does not ratchet up (1,800-scan run: 1.8 GB without, ~0.55 GB flat with,
    ~16 ms a trim). 0: never."""


class PoseStartConfig(StrictModel):
    """The start of the static refinement: ``FlowToPose`` on the network's static flow.

    Only a start for the ICP, so it is registered cheaply: the fields below replace
    those of ``flow_odometry:``, every other field is taken from there."""

    max_points: int = Field(5000, ge=0)
    """Static flow pairs registered (seeded random subsample; 0 = all)."""
    ransac_below_inlier_ratio: float = Field(0.0, ge=0, le=1)
    """RANSAC rescue below this inlier share (0: never; the refinement registers again)."""
    check_geometry: bool = False
    """Run the corridor degeneracy check (the refined registration runs it anyway)."""


class FlowRefinementConfig(StrictModel):
    """Static refinement: flow-guided point-to-plane ICP of the static points onto scan k,
    each static point then snapped onto scan k's tangent plane."""

    enabled: bool = True
    """False: the odometry uses the network's static flow as it is."""
    voxel_m: float = Field(0.4, gt=0)
    """Voxel size of the downsampled source and target clouds."""
    max_range_m: float = Field(80.0, gt=0)
    """Points farther from the sensor are not used."""
    correspondence_m: list[float] = Field(default_factory=lambda: [1.0, 0.3])
    """ICP stages, coarse to fine: largest correspondence distance per stage."""
    max_iterations: int = Field(30, ge=1)
    """ICP iterations per stage."""
    max_source_points: int = Field(4000, ge=10)
    """At most this many downsampled static source points (a seeded random subset)."""
    normal_radius_m: float = Field(1.2, gt=0)
    """Neighbourhood radius (at most 20 points) of the target normals."""
    max_surface_variation: float = Field(0.02, gt=0, le=1)
    """Target points whose neighbourhood is not a plane are left out: surface variation
    ``l0 / (l0 + l1 + l2)`` (eigenvalues of the neighbourhood's covariance, 0 for a plane,
    1/3 at most) above this. Their normals are tilted (curbs, the feet of walls, cars) and,
    with the in-plane offsets of ring sampling, biased every step (docs/mapping.md)."""
    min_plane_spread: float = Field(0.2, ge=0, le=1)
    """... and those whose neighbourhood is a line rather than a plane (middle eigenvalue
    below this share of the largest: a stretch of one ring on the ground, whose smallest
    axis lies anywhere across it and, with range noise, tilts towards the radial
    direction) are asked again (``line_radius_m``). 0: off. Simulated `dt` on the 32-beam
    vlp32c pitched 0.05-0.12 deg down at every step (KISS-ICP: 0.01). Tuning seeds 242 /
    252 (stop 35): EPE3D 0.0196 / 0.0157 -> 0.0124 / 0.0110 m, rotation error ~0.07 / 0.05
    -> ~0.01 deg per step; the AV2 pair's EPE3D 0.0175 -> 0.0130 m (rotation 0.055 -> 0.011
    deg, translation 3.4 -> 7.7 mm); KITTI 0-15 RPE(1) against the ICP reference 1.198 ->
    1.201 cm."""
    line_radius_m: float = Field(3.5, ge=0)
    """A line-like target point (``min_plane_spread``) is asked again with the neighbours
    within this radius (m, at most 40): across the gap to the next ring, its neighbourhood
    is a plane, and it keeps that plane's normal. 0: line-like points are left out
    (measured: the AV2 pair's translation error 3.4 -> 11.1 mm and its FD 0.216 -> 0.433;
    KITTI RPE(1) 1.218 cm). 1.8 / 2.5 / 3.5 / 5.0 m: the AV2 pair's translation error
    10.5 / 9.8 / 7.7 / 9.9 mm, KITTI 0-15 RPE(1) - / 1.244 / 1.201 / 1.309 cm, `dt` 242
    EPE3D - / 0.0135 / 0.0124 / 0.0115 m."""
    dynamic_exclusion_m: float = Field(0.6, ge=0)
    """Target points this close to a predicted dynamic landing point are left out."""
    min_fitness: float = Field(0.3, ge=0, le=1)
    """Refinement rejected (network flow kept) when fewer source points find a partner."""


class MotionEvidenceConfig(StrictModel):
    """Geometric movers: points that leave scan k's surface under the ego motion and lie
    where a range image of scan k sees through (degrees for the image bins)."""

    enabled: bool = True
    """Add geometric movers to the objects' candidates."""
    max_range_m: float = Field(110.0, gt=0)
    """Points farther than this (horizontal distance, m) are not tested. 70 m (was 40) with
    ``objects.max_range_m`` 80 and ``objects.instance_gap_rad`` 0.02, adopted by a rule
    written before fresh seeds (stop 50): fresh ``dt`` 541-544 all-points instance recall
    +0.026 to +0.092, precision within 0.011, EPE3D and Dynamic IoU not worse. 110 m (stop 72):
    the simulated sensors reach 120 m, and on tuning ``dt`` 1008 56 of 273 missed GT object-pairs
    were vehicles beyond 80 m, none of them a candidate.
    Adopted by rule 24 with ``baseline_row_from_m`` (see there)."""
    azimuth_resolution_deg: float = Field(0.4, gt=0)
    """Azimuth bin of the range image."""
    elevation_resolution_deg: float = Field(0.4, gt=0)
    """Elevation bin of the range image."""
    window: int = Field(1, ge=0)
    """Half-size of the bin window that must all see beyond the point (1: 3x3 bins)."""
    own_bin_from_m: float | None = Field(None, ge=0)
    """Points whose ego-moved position lies at least this far from the sensor (horizontal
    range, m) are seen through when their own bin sees beyond them, not the whole window:
    far off, the window spans more than a crossing vehicle leaves in one scan (3 bins of
    0.4 degrees: ~0.8 m at 37 m). None: the window everywhere. Stop 65, rule 7 (30 m, opt-in):
    fresh ``dt`` 771 / 772 all-points instance recall +0.005 / +0.022 (clause: a mean of 0.02),
    nothing lower inside the flow region; with the gated track reach (rule 8) fresh ``static``
    784 called more points dynamic (docs/sceneflow_evaluation.md)."""
    margin_m: float = Field(0.3, ge=0)
    """A return is beyond a point at range r when farther than r + margin_m + relative_margin r ..."""
    relative_margin: float = Field(0.02, ge=0)
    """... (the relative part of that margin)."""
    off_surface_m: float = Field(0.25, gt=0)
    """A point is off scan k's surface when its ego-moved position has no scan-k point this close."""
    ground_cell_m: float = Field(2.0, gt=0)
    """BEV cell of the ground estimate (lowest point per cell)."""
    ground_clearance_m: float = Field(0.3, ge=0)
    """Points less than this above the ground estimate are never movers."""
    max_height_m: float | None = Field(None, gt=0)
    """Points more than this above the ground estimate are not tested either (seen-through,
    off-surface, slow-mover and arrival tests): what moves stands lower (the simulator's box
    truck: 3.2 m), the tree canopies that the tests flag from a sparse sensor's scans do not.
    None: no ceiling. Stop 65, rule 9 (2.5 m, opt-in): fresh ``static`` 791-794 0.112 -> 0.105 %
    of points dynamic on average (clause: 0.9x), nothing else changed for the worse; tuning
    ``static`` 784 0.281 -> 0.146 % (docs/sceneflow_evaluation.md)."""
    cluster_cell_m: float = Field(0.4, gt=0)
    """BEV cell of the movers' connected-component clustering."""
    min_points: int = Field(15, ge=1)
    """Clusters with fewer points are dropped."""
    min_seen_through: int = Field(5, ge=1)
    """... and clusters with fewer seen-through points."""
    min_points_far: int | None = Field(None, ge=1)
    """Clusters whose points lie ``far_from_m`` or farther on average (horizontally) need only
    this many instead of ``min_points``: a sensor's returns thin out with range (a truck at 40 m
    on a 16-beam sensor: 8-14 points that an older scan sees through). None: ``min_points``
    everywhere. See ``ObjectRefinementConfig.min_points_far``. 10 in both, with
    ``slide_free_share`` 0.25: tuning ``dt`` 1079 / 1080 all-points recall +0.016 / +0.019; rule
    29 failed on fresh seeds (``dt`` 1091-1093 mean +0.002, 1091 precision -0.0075), so opt-in
    (docs/sceneflow_evaluation.md, stop 75)."""
    far_from_m: float = Field(30.0, ge=0)
    """... the range (m) from which ``min_points_far`` applies."""
    max_extent_m: float = Field(12.0, gt=0)
    """... and clusters whose BEV extent (diagonal) exceeds this (walls, not vehicles)."""
    baseline_scans: int = Field(7, ge=0)
    """Slow movers: the points of scan k-1 are also tested against the scan this many scans
    older (placed with the frontend's own poses): a cluster of at least ``min_points``
    points where that scan sees through is a candidate object. Walkers and slow cars
    (5-10 cm per scan) never leave scan k's surface in one step, but do in several. The
    objects stage keeps each scan's range image and own pose from when it was scan k, so
    the baseline may reach beyond the network's window; until a run has seen that many
    scans, the window's oldest scan serves. 0: off."""
    hidden_baseline_scans: int = Field(0, ge=0)
    """Opt-in: where the scan ``baseline_scans`` before scan k-1 did not see a point (something
    stood more than ``baseline_vacated_max_m`` in front of it there), the slow-mover test's
    flags against the newer scan this many scans before scan k-1 count for that point. A
    trace of tuning ``dt`` 878 (stop 68): 20 of 40 frames of near walkers with no candidate
    point were hidden from the older scan's viewpoint. Prototype with 4 on the tuning seeds:
    all-points recall +0.003 / +0.006 on ``dt`` 878 / 877, ``static`` 784 unchanged. Rule 15
    failed on fresh seeds: ``dt`` 917-919 mean recall +0.0009 (clause +0.003), KITTI objects
    stage 1.13x, more ``rush-hour`` ID switches (docs/sceneflow_evaluation.md). 0: off."""
    long_baseline_scans: int = Field(14, ge=0)
    """Slow movers a second time, against the scan this many scans before scan k-1 (as kept
    from when it was scan k; skipped until a run has seen that many scans, so the
    ``baseline_scans`` test alone covers the warm-up): a walker at 0.5-0.8 m/s moves
    0.35-0.56 m in 7 scans, about its own width, and twice that in 14; a car sliding along
    its own side leaves its older place only over a longer baseline. 0: off. 14 with
    ``long_baseline_from_m`` 20, adopted by rule 14 (stop 68), written before fresh seeds:
    fresh 100-scan ``dt`` 897 / 898 / 899 Dynamic IoU +0.001 / +0.026 / +0.001, all-points
    instance recall +0.001 / +0.019 / 0; fresh ``static`` 891-896 1.05x the points dynamic
    (0.057 -> 0.059 %); ``rush-hour`` 900-902 not worse (docs/sceneflow_evaluation.md)."""
    long_baseline_from_m: float = Field(20.0, ge=0)
    """... only for points of scan k-1 at least this far (horizontal range, m): nearer, the
    short baseline's free space already finds slow walkers (its margins and bins are small
    there), and from far back the long one sees around the edges of near static bodies
    (tuning ``static`` 784: parked cars at 7-12 m then slid along themselves; 0.070 ->
    0.113 % of points dynamic with no floor, 0.076 % with 15 m, 0.072 % with 20 m)."""
    baseline_own_bin: bool = False
    """Opt-in: that test looks at each point's own range-image bin, with the margins below,
    instead of the seen-through test's window and margins. Measured (stop 28): more slow
    walkers found (fresh `dt` recall 0.46 -> 0.67), more static objects called moving
    (fresh `static` 0.14 -> 0.45 % of points). Stop 62, with margins 0.5 m and 0.03: fresh
    `dt` 721 / 722 region recall 0.848 / 0.725 -> 0.840 / 0.761, `static` 724 / 725 at most
    0.10 % dynamic; under its rule's +0.02 mean recall, so still opt-in."""
    baseline_row_from_m: float | None = Field(40.0, ge=0)
    """The free-space test against an older scan (``baseline_own_bin`` false) looks at
    each point's row of the window -- its own elevation bin and its azimuth neighbours --
    where the point lies at least this far from the older scan's sensor (horizontal range, m).
    Far off, the window's elevation neighbours are other rings, whose returns from the ground
    in front of a vehicle keep the window from seeing beyond it: on tuning ``dt`` 1008, 85 of
    108 vehicle-pairs at 40-80 m were missed, and the older scan's window saw beyond 17 % of a
    crossing vehicle's points, its own bins 37 %. Each point's own bin alone (stop 72, rule 23)
    also moved a static object 50 m behind the sensor on real KITTI 0-15; the row keeps the
    azimuth neighbours. None: the window everywhere.
    Adopted by rule 24 (stop 72), written before fresh seeds, together with ``objects.max_range_m``
    120, ``motion_evidence.max_range_m`` 110, ``baseline_row_from_m`` 40 and ``grow_movers_from_m``
    40: fresh 100-scan ``dt`` 1037 / 1038 / 1039 all-points instance recall +0.017 / +0.020 / 0,
    nothing worse on fresh ``static`` 1031-1036 or ``rush-hour`` 1040-1042, KITTI objects stage
    1.018x (docs/sceneflow_evaluation.md)."""
    baseline_vacated: bool = True
    """Slow movers also where the older scan saw something in front of the point (the
    nearest return of the seen-through test's window, at most ``baseline_vacated_max_m`` in
    front) whose place, on the point's ray, scan k-1 sees through now (its range image, kept
    from when it was scan k): what stood in front has left, as a walker walking away from
    the sensor leaves the place just in front of where it is now. Tuning seeds: `dt`
    Dynamic IoU +0.00-0.03, recall +0.00-0.05; `static` and `rush-hour` unchanged within
    0.001 % of points / 0.2 % AccStrict."""
    baseline_vacated_max_m: float = Field(1.5, gt=0)
    """... (m): a slow mover moves less than this in ``baseline_scans`` scans; what lies
    farther behind the place that was left is what the leaving revealed (a wall behind the
    walker), not what arrived (3.0: `dt` recall +0.00-0.04 more, `static` 243 0.067 ->
    0.074 % of points dynamic, `rush-hour` 234 EPE3D 0.0364 -> 0.0368)."""
    baseline_vacated_window_from_m: float | None = Field(10.0, ge=0)
    """Beyond this range (m, in the older scan's frame) the vacated test uses the windowed
    test's margins below (``baseline_window_*``) instead of the seen-through test's, both
    for what the older scan saw in front and for scan k-1 seeing through its place: a
    walker walking away at 1 m/s leaves 0.7 m in 7 scans, less than 0.3 m + 2 % of the
    range beyond 20 m. Nearer, the wider margins stay. None: the seen-through test's
    margins everywhere. Stop 39: tuning `dt` 381 / 382 Dynamic IoU +0.014 / +0.008,
    instance recall in the flow region +0.031 / +0.025, but `dt` 362 -0.009 (hedges a
    walker revealed: precision 0.953 -> 0.932); fresh `dt` 411 / 412 IoU +0.009 / +0.007,
    recall +0.047 / +0.008; `rush-hour`, `static` and the AV2 pair unchanged."""
    baseline_window_margin_m: float | None = Field(None, ge=0)
    """The windowed test against the older scan (``baseline_own_bin`` false): its returns
    must lie farther than the point by this (m) ... (None: ``margin_m``)"""
    baseline_window_relative_margin: float | None = Field(0.005, ge=0)
    """... plus this share of the point's range (None: ``relative_margin``). A walker
    walking towards the sensor at 0.9 m/s comes 0.6 m nearer in 7 scans; the seen-through
    test's 0.3 m + 2 % is 0.8 m at 25 m. 0.005 (stop 35, tuning `dt` 241/242/251/252):
    Dynamic IoU +0.002-0.012, instance recall +0.005-0.015; `static` and `rush-hour`
    unchanged within 0.005 % of points / 0.04 % AccStrict. A margin of 0.15 m as well
    cost `dt` 242 0.03 of precision."""
    arrivals: bool = True
    """Movers also where scan k fills scan k-1's free space: the off-surface points of scan
    k-1 form a mover cluster when, within it, at least ``min_seen_through`` points of scan k
    lie where scan k-1's range image (kept from when it was scan k) saw clearly beyond them
    -- an object coming towards the sensor hides its old place behind its new one, so the
    seen-through test never fires on it. Those points also count as seen through (the
    objects' shifted starts). The real AV2 pair: two cars approaching at 27-29 m (0.4 and
    0.8 m per scan) found; 3-way EPE 0.078 -> 0.067, FD 0.216 -> 0.183, Dynamic IoU 0.620 ->
    0.700 (docs/sceneflow_evaluation.md, stop 36)."""
    arrival_margin_m: float = Field(0.15, ge=0)
    """An arrival lies nearer than scan k-1's returns, in the seen-through test's window and
    in its own bin, by this (m) ..."""
    arrival_relative_margin: float = Field(0.005, ge=0)
    """... plus this share of its range (the seen-through test's 0.3 m + 2 % is 0.86 m at
    28 m, more than a car at 4.4 m/s comes nearer in a scan)."""
    arrival_min_range_m: float = Field(10.0, ge=0)
    """Arrival clusters nearer than this (horizontal distance of their centre, m) are not
    movers. Real KITTI 0-15: 5 of the 6 arrival clusters lay within 10 m, on parked cars
    (the beams that cross their windows) and a fence; one made a parked car beside the ego
    move (562 points). Near movers leave scan k's surface by more than the seen-through
    test's margin."""
    baseline_margin_m: float = Field(0.15, ge=0)
    """With ``baseline_own_bin``: the older scan's return must lie farther than the point
    by this ..."""
    baseline_relative_margin: float = Field(0.01, ge=0)
    """... plus this share of the point's range."""


class ObjectRefinementConfig(StrictModel):
    """Objects stage: candidate moving points clustered, each object registered to scan k
    by its own rigid ICP; static when the ego motion explains it as well."""

    enabled: bool = True
    """False: static points get the rigid flow of the measurement, the rest the network's flow."""
    max_range_m: float = Field(120.0, gt=0)
    """Candidates farther than this (xy, m) are left as the network said (80 m, was 50:
    with ``motion_evidence.max_range_m`` 70 and ``instance_gap_rad`` 0.02, stop 50; 120 m with
    ``motion_evidence.max_range_m`` 110, stop 72, rule 24)."""
    min_range_m: float = Field(2.0, ge=0)
    """... and those nearer than this (xy): returns of the ego vehicle's own body, which
    move with the sensor (real KITTI frames 0-15: 15-25 points at 1.4-1.8 m, behind the
    sensor on both sides, in every scan: a "track moving with the car"). 2.5 m cut into
    crowds beside the car in simulated `rush-hour` 143 (AccStrict 71 -> 67 %,
    docs/sceneflow_evaluation.md)."""
    off_surface_m: float = Field(0.3, ge=0)
    """A network-dynamic point outside every accepted object becomes static when its
    ego-rigid landing spot is this close to a scan-k point."""
    cluster_cell_m: float = Field(0.6, gt=0)
    """BEV grid cell of the connected-component clustering (8-connected)."""
    min_points: int = Field(15, ge=3)
    """Clusters with fewer points are not registered."""
    min_points_far: int | None = Field(None, ge=3)
    """Candidate clusters whose points lie ``far_from_m`` or farther on average (horizontally)
    are registered from this many geometric movers (``motion_evidence.min_points_far`` lets the
    geometric tests' flags of such clusters through; the network's candidates alone still need
    ``min_points``). None: ``min_points`` everywhere."""
    far_from_m: float = Field(30.0, ge=0)
    """... the range (m) from which ``min_points_far`` applies."""
    min_above_ground_points: int = Field(5, ge=0)
    """Clusters with fewer points than this higher than ``motion_evidence.ground_clearance_m``
    above the local ground are road, not objects: static, no ICP. A ring's arc on flat
    ground maps onto itself under a turn about the sensor's axis, so point-to-point ICP
    "registers" it anywhere along the ring (real KITTI: 1-m-long arcs at 33-46 m registered
    with turns of up to 180 deg and called moving, docs/sceneflow_evaluation.md). 0: no test."""
    min_rings: int = Field(3, ge=0)
    """An object whose points lie on fewer of the sensor's rings than this (elevation
    angles from scan k-1's origin more than ``ring_gap_rad`` apart,
    :func:`~flowslam.sceneflow.refinement.clusters.ring_count`), inside a body that lies on
    more (``ring_body_m``), is static, without an ICP: one or two scan lines across a curved
    surface (a tree's canopy, a parked car's flank) slide onto scan k's neighbouring lines
    under ICP, and the slide was called motion (``static`` 784: tracked canopy arcs at 16-23
    m for 14 pairs; points called dynamic 0.278 -> 0.09 %). Adopted with ``ring_body_m``
    1.5 by a rule on fresh seeds of three sensors (docs/sceneflow_evaluation.md, stop 66):
    fresh ``static`` 831-837 mean 0.202 -> 0.127 % dynamic; ``dt`` 841-843 Dynamic IoU
    +0.000 / +0.006 / +0.012; ``rush-hour`` 844-846 EPE3D within 0.1 mm; KITTI 0-15 and the
    AV2 pair unchanged. 0: no test."""
    ring_body_m: float = Field(1.5, ge=0)
    """With ``min_rings``: an object on too few rings stays static only when the points
    clear of the ground within this distance (m) of it, its own included, lie on at least
    ``min_rings`` rings: a slice of a larger body (a canopy's arc, a car's flank), not an
    object thin as a whole (a vehicle on a 16-beam sensor's two rings). 0: every object on
    too few rings -- which cost a vlp16 ``dt`` (821) 0.08 of instance recall (stop 66)."""
    ring_gap_rad: float = Field(0.00175, gt=0)
    """Two neighbouring elevation angles further apart than this (rad; 0.1 deg) lie on
    different rings (``min_rings``)."""
    instance_cell_m: float = Field(0.3, gt=0)
    """The moving points of an object that share a motion are split into BEV connected
    components of this cell (8-connected), each of at least ``min_points``, as separate
    instances (people walking side by side; smaller components join the largest);
    ``cluster_cell_m`` or more: no split. 0.3 against 0.6: instance recall `dt` 126
    0.46 -> 0.50, `rush-hour` 124 0.37 -> 0.61 (docs/sceneflow_evaluation.md)."""
    instance_gap_rad: float = Field(0.02, ge=0)
    """Components of one motion within an object (``instance_cell_m``) are also joined where
    their points come within this angle (rad) times the group's median range (BEV, m) of
    each other, when that is wider than the cell: far away the beams sample a car's faces
    farther apart than ``instance_cell_m``, and one car fell into two instances at 47 m
    (docs/sceneflow_evaluation.md, stop 49). 0: no joining. Tuning ``dt`` 533 with the far
    ranges: 0 / 0.0125 / 0.02 / 0.03 gave recall 0.727 / 0.725 / 0.752 / 0.745, precision
    0.912 / 0.898 / 0.945 / 0.934 (stop 50)."""
    split_above_ground: bool = True
    """One motion's moving points of an object are split into the components of those clear
    of the local ground (``motion_evidence.ground_clearance_m``), each point near the ground
    joining the component of its nearest such point (BEV), when that gives more components,
    each at most a person wide (1.2 m): walkers whose feet, or the ground flagged between
    them, touch. Adopted by a rule written before fresh seeds (stop 50): fresh
    ``rush-hour`` 551 / 552 instance recall 0.722 / 0.809 -> 0.738 / 0.808, precision
    0.891 / 0.910 -> 0.899 / 0.910; ``dt`` 553 / 554 and ``static`` 555 unchanged
    (docs/sceneflow_evaluation.md)."""
    split_people: bool = True
    """Moving points of one motion that touch in BEV but hold several heads (walkers close
    together in a crowd) are split into one instance per head
    (:func:`flowslam.sceneflow.refinement.objects._people`); instance ids only, the flow and
    the labels are not changed. Fresh ``rush-hour`` 274 / 275: instance recall 0.598 /
    0.547 -> 0.662 / 0.614, precision 0.843 / 0.820 -> 0.869 / 0.850; ``dt``, ``static``,
    the real AV2 pair and KITTI unchanged (docs/sceneflow_evaluation.md)."""
    people_core_share: float = Field(0.7, ge=0)
    """With ``split_people``: an instance with two or more heads is also split when at least
    this share of its points lie within 0.6 m (BEV) of a head and each head has
    ``min_points`` such points, however wide the stray rest makes a group
    (:func:`flowslam.sceneflow.refinement.objects._around_heads`); above 1: only when every
    group is at most a person wide. Instance ids only. Adopted by a rule written before
    fresh seeds (stop 51): fresh ``rush-hour`` 561 / 562 instance recall 0.699 / 0.777 ->
    0.734 / 0.805, precision 0.872 / 0.922 -> 0.892 / 0.935; ``dt`` 563 / 564 and ``static``
    565 unchanged (docs/sceneflow_evaluation.md)."""
    unregistered_instances: bool = True
    """Dynamic points beyond ``min_range_m`` that no accepted object holds (a cluster whose
    ICP was not accepted, or the network's movers outside every cluster, each kept dynamic
    because its ego landing is off scan k's surface) become instances too: grouped by the
    cluster they were in (else by ``cluster_cell_m`` BEV clusters) and split as the
    registered ones (:func:`flowslam.sceneflow.refinement.objects._parts`,
    ``split_people``), each of at least ``min_points`` (smaller fragments keep no
    instance); their flow and labels are not changed. False: they stay dynamic without an
    instance (no row in ``moving_objects.csv``). Adopted by a rule written before fresh
    seeds (stop 52): fresh ``rush-hour`` 591 / 592 instance recall 0.793 / 0.817 -> 0.814 /
    0.855, precision 0.904 / 0.931 -> 0.898 / 0.928; ``dt`` 593 recall 0.745 -> 0.754, 594
    and ``static`` 595 unchanged; real KITTI 0-15: 37 -> 42 instances of >= 15 points over
    15 pairs (docs/sceneflow_evaluation.md)."""
    rest_min_speed_mps: float = Field(0.5, ge=0)
    """> 0: dynamic points beyond ``min_range_m`` that no accepted object holds (their ego
    landings off scan k's surface) become static, with the ego motion's flow, where their
    group (the object whose ICP was not accepted, else a ``cluster_cell_m`` BEV cluster)
    does not move by its own flow: the median departure of its landings from the ego
    landings is at most this speed (m/s; horizontally with ``horizontal_departure``), and
    none of its points is a geometric mover or seen through (``motion_evidence``). In
    static scenes that is where the network's slow false movers stay dynamic. 0: off.
    Adopted by a rule written before fresh seeds (stop 67, rule 13): fresh ``static``
    871-876 (hdl64, vlp32c, vlp16) 0.117 -> 0.093 % of points dynamic; ``dt`` 877-879 and
    ``rush-hour`` 880-882 within their clauses; KITTI and AV2 unchanged. Without the
    evidence exclusion (rule 12, 0.25 m/s) the fresh gain was 7.8 %, under its 10 %
    (docs/sceneflow_evaluation.md)."""
    split_extent_m: float = Field(8.0, ge=0)
    """Clusters wider than this (BEV diagonal, m; 0: never) are also registered as their
    ``instance_cell_m`` components (at least ``min_points`` each), which replace the cluster
    when they explain at least ``split_gain`` more of its points: one rigid motion cannot
    register the several movers of a crowd or a queue. Measured (stop 30, 8 m):
    ``rush-hour`` 143 / 164 / 174 / 184 EPE3D 0.0706 / 0.0449 / 0.0584 / 0.0559 -> 0.0554 /
    0.0435 / 0.0450 / 0.0488; the real AV2 pair, ``dt`` 126 / 171 and ``static`` 173
    unchanged. Splitting every wide cluster (stop 29) took the AV2 pair's 3-way EPE from
    0.084 to 0.109: a car beside the ego whose sparse candidates fell into several
    components, each sliding along its own faces."""
    split_gain: float = Field(0.05, ge=0)
    """A cluster wider than ``split_extent_m`` is replaced by its components when their
    registrations put at least this share of its points more on scan k's surface than
    its own does."""
    tracked_parts_min_points: int = Field(15, ge=0)
    """> 0: where a cluster ends with no moving point but holds points the mover track
    carried from the last pair and the network flags too (at most ``tracked_parts_max_share``
    of it; a track the network does not confirm is left to the track's own rules), each
    ``instance_cell_m`` component of those points with at least this many is registered on
    its own, and the ones that then move leave the cluster as objects of their own (the rest
    keeps the cluster's result). In a crowd the network's candidates join walkers and the
    static scene around them into one cluster of thousands of points, whose single ICP is
    the ego motion. 0: off. Adopted by rule 20, written before its fresh seeds (stop 70):
    fresh ``rush-hour`` 981-986 all-points instance recall +0.0061 on average (hdl64 +0.008 /
    +0.014, vlp32c +0.005 / +0.004, vlp16 -0.002 / +0.008), ``dt`` 987-989 and ``static``
    990-992 within their clauses, KITTI and AV2 unchanged. Rules 18 and 19 (before the
    network's confirmation was asked) failed: too small a gain, and track-only parts that
    were static (docs/sceneflow_evaluation.md)."""
    tracked_parts_max_share: float = Field(0.8, gt=0, le=1)
    """The largest share of a cluster its tracked points may hold for
    ``tracked_parts_min_points`` to look at them on their own (a cluster that is mostly
    tracked was registered as the tracked object already)."""
    correspondence_m: list[float] = Field(default_factory=lambda: [1.0, 0.3, 0.1], min_length=1)
    """Per-object ICP stages, coarse to fine: largest correspondence distance per stage (at
    least one)."""
    max_iterations: int = Field(15, ge=1)
    """ICP iterations per stage."""
    max_turn_rad: float = Field(0.52, ge=0)
    """An object's ICP from one start is given up as soon as an iteration turns it farther
    than this (rad, ~30 deg) from its start's rotation (the ego rotation): a vehicle does
    not turn 30 deg in 0.1 s, and such a registration is a sparse object spinning into
    other structure, or a walker flipped about its axis (picked results turned up to 180
    deg on simulated `dt` and `rush-hour`). Adopted by a rule written before fresh seeds
    (stop 62): fresh `dt` 711 / 712 and `rush-hour` 713 EPE3D -4.8 / -3.2 / -2.2 %, Dynamic
    IoU and recall within 0.003; `static` 714, KITTI 0-15 and the real AV2 pair unchanged;
    KITTI objects stage ~4 % faster. 20 deg changed the AV2 pair's 3-way EPE 0.046 -> 0.088
    (a car that turns on its way to its motion). 0: no limit."""
    prefer_first_start: bool = True
    """Of an object's ICP starts, the first (its network or tracked displacement) keeps its
    result unless another start's result has more fitness by the margin of
    ``static_preference`` / ``static_preference_sigmas``, or lands the object within 3 cm
    of it (the same solution): the other starts (ego landings shifted along the object's
    axis, ``hypotheses_m``) are there to recover from a wrong first start, and a vehicle
    sliding along its own side fits scan k about equally well anywhere along the slide
    (`rush-hour` 234: a car beside the ego, first start 1 cm from the truth, a shifted
    start won by 0.4 % of fitness and put it 14 cm off). `rush-hour` 234 / 245 AccStrict
    0.862 / 0.869 -> 0.870 / 0.889; `dt`, `static`, the real AV2 pair and KITTI unchanged
    (docs/sceneflow_evaluation.md). False: the plain (fitness, -RMSE) best."""
    plane_stage_radius_m: float = Field(0.3, ge=0)
    """> 0: each motion an object keeps as its own (not explained by the ego motion) is
    polished by one point-to-plane ICP at the finest correspondence distance, on target
    normals estimated within this radius (m), and keeps the polish when it keeps the object on
    the ground and fits scan k as tightly (inlier RMSE no larger) with about as many points
    (fitness lower by at most the margin of ``static_preference`` /
    ``static_preference_sigmas``); 0: off. Until stop 33 the polish had to reach the same
    fitness as well: `rush-hour` 234 / 245 AccStrict 0.870 / 0.889 -> 0.887 / 0.893, `dt`
    242 EPE_FD 0.0707 -> 0.0692, `static`, the real AV2 pair and KITTI unchanged."""
    planar_motion: bool = True
    """The polished motion (``plane_stage_radius_m``) is replaced by the motion nearest to it
    (least squares over the object's points) that turns the object only about scan k's z
    axis relative to its ego landing: objects move on the ground, and within 0.1 s a
    vehicle does not roll or pitch; a free ICP of a partly seen car does, by a degree or
    two (simulated `rush-hour` 234: failing objects tilted by a median 2 deg against the
    truth, 0.2-0.5 deg for the others). `rush-hour` 234 / 245 AccStrict 0.887 / 0.893 ->
    0.891 / 0.895, `dt` 241 Dynamic IoU 0.793 -> 0.787, `dt` 242, `static`, the real AV2
    pair unchanged. Applied to every ICP result instead (not only the polished ones),
    `rush-hour` gained a little more but the real AV2 pair lost (3-way EPE 0.082 -> 0.087,
    Dynamic IoU 0.611 -> 0.601): a projection without a new fit can leave a poorly spread
    mover subset off its surface (docs/sceneflow_evaluation.md)."""
    mover_part_cell_m: float = Field(1.0, ge=0)
    """> 0: an object whose geometric movers fall into several BEV components of this cell
    (m), each wider than a walker (``PERSON_MAX_EXTENT_M``) and of at least ``min_points``,
    registers each component's movers on its own, from starts along that component's axis,
    instead of all its movers at once: two vehicles that drive apart side by side form one
    cluster, and one rigid motion of both is a turn about a point between them (the real AV2
    pair: two cars at 27 m, 1.1 m per scan apart, one motion turned 10 deg). 0: one set.
    Stop 37, with ``coherent_parts`` and ``leftover_motion``: docs/sceneflow_evaluation.md."""
    coherent_parts: bool = True
    """An object with several motions gives each point clear of the ground the motion that
    most points of its ``instance_cell_m`` BEV component took among those only one motion
    lands on scan k's surface, when that motion lands it near scan k too; else each point
    takes the motion nearest to scan k. A car's roof and sides fit a neighbouring car's
    motion as well (they slide along themselves); only its ends tell."""
    leftover_motion: bool = True
    """An object with a motion of its own also registers the points that neither the ego
    motion nor any of its motions lands on scan k's surface, when they are at least
    ``min_points`` and ``leftover_share`` of it, from their input flow's median displacement;
    their motion is kept when it fits (``min_fitness``, ``max_rmse_m``) and the ego motion
    does not explain them as well. Tuning `rush-hour` 364 EPE3D 0.0405 -> 0.0359 with the two
    options above; the AV2 pair unchanged by it."""
    whole_motion_slow_share: float = Field(0.0, ge=0)
    """An object whose movers got a motion of their own drops its whole-body motion when
    that moves it (mean horizontal departure from the ego landings) by at most this share of
    the slowest of its movers' motions and lands no more of its points on scan k's surface
    (within ``score_plane_m``) than the ego motion and the movers' motions together, by the
    fitness margin (``static_preference``, ``static_preference_sigmas``). A near car merged
    with the static points around it: an ICP of the whole cluster may shift it by a few
    centimetres towards the car's motion, fit it slightly better than the ego motion, and
    move its static points. 0: off."""
    grow_wide_margin: float = Field(0.2, ge=0)
    """A component wider than ``grow_max_extent_m`` does not join a moving object, but its
    ``instance_cell_m`` parts (each at most that wide) that hold the object's dynamic points
    may: the object's motion is refitted on such a part (point-to-point ICP from it, onto
    scan k within ``margin_m``) and the part joins when the refit puts at least this share
    more of it on scan k's surface than the ego motion (the coarser cell joined a vehicle to
    the trees or a fence beside it; a static part must not join). > 1: off. The real AV2
    pair: a car at 29 m in a 15.8 m component with trees, refit 0.67 vs ego 0.32 of its part
    on the surface: 3-way 0.0621 -> 0.0535, FD 0.1683 -> 0.1425, Dynamic IoU 0.706 -> 0.777.
    With the usual ``static_preference`` margin instead, on simulated `dt` 362 (vlp32c) parts
    of walls joined (refit 0.91 vs ego 0.85) and 819 static points moved (Dynamic IoU
    0.853 -> 0.844); with 0.2 the tuning seeds are unchanged (stop 37)."""
    grow_wide_ego_near_m: float = Field(0.0, ge=0)
    """> 0: such a part does not join when at least ``grow_wide_ego_near_share`` of its ego
    landings lie within this (m) of a scan-k point: the ego motion puts it on scan k, and a
    refit that puts more of it on scan k's tangent planes fits rough normals, not motion. Fresh
    vlp16 ``static`` 1035 (stop 72): a bush on six rings at 14 m joined a false mover with 342
    points (refit 0.99 vs ego 0.70 on the planes, 99 % of its ego landings within 0.3 m of a
    scan-k point): 0.564 -> 0.331 % of points dynamic with 0.3 m; of the other tuning seeds only
    ``dt`` 1008 changed (recall +0.0007). Rule 25 failed: no fresh seed changed (1043-1054). 0: off."""
    grow_wide_ego_near_share: float = Field(0.95, gt=0, le=1)
    """... (the share of ``grow_wide_ego_near_m``)."""
    grow_unexplained: bool = True
    """When a component joins a moving object (``grow_max_extent_m``, ``grow_footprint_cell_m``),
    its points that neither the object's motion nor the ego motion puts on scan k's surface
    (hidden in scan k: a car's far side, its lower edge) join too, with the object's motion;
    points only the ego motion explains stay static. False: only the points the motion
    explains join. The real AV2 pair: 3-way 0.0634 -> 0.0621, FD 0.1723 -> 0.1683,
    Dynamic IoU 0.700 -> 0.706; tuning `dt` 361 / 362, `rush-hour` 364, `static` 363 within
    0.0003 of IoU and 0.0001 m of EPE3D (stop 37)."""
    min_discriminating_share: float = Field(0.05, ge=0, le=1)
    """An object without free-space evidence (fewer seen-through points than ``min_seen_through``
    or 2 % of its points, ``SEEN_EVIDENCE_SHARE``) keeps a motion of its own only when at least
    this share of its landings (of those with a normal) lie on scan-k surfaces that face along the
    motion (normal within 60 degrees of its departure from the ego landings); 0: off. A wall
    or fence slid along itself fits anywhere along the slide, and its fit says nothing (the
    KITTI double wall, simulated fences). Walkers are left out (objects at most
    ``FOOTPRINT_MAX_EXTENT_M`` across moving at most ``WALKER_MAX_SPEED_MPS``): a walker
    beside a fence forms one small object with it, whose motion the fence's normals cannot
    judge."""
    hold_tracks: bool = True
    """A tracked mover (the last pair's moving points, moved on with their own motion) that
    this pair's tests leave static keeps moving with its predicted flow when, per BEV
    component (``instance_cell_m``) of at least ``min_points`` tracked points: the
    prediction moves it (more than ``dynamic_speed_mps``), lands at least ``min_fitness``
    of it on scan k's surface and no less than ``static_preference`` below the ego
    motion's share, and the scan ``motion_evidence.baseline_scans`` back (placed with the
    frontend's own poses) saw through at least ``hold_free_share`` of its points (the
    slow-mover test's window and margins, ``baseline_window_margin_m`` and
    ``baseline_window_relative_margin``): something has arrived there since. One scan moves
    a walker by about the plane tolerance, so one pair cannot tell it from a static body it
    walks along; the older scan can (where it saw something in front instead, nothing is
    known, and nothing is held: a fence hidden behind a parked car)."""
    hold_free_share: float = Field(0.3, ge=0, le=1)
    """See ``hold_tracks``. Each point's own bin instead of the window held static objects
    of the vlp32c `dt` 362 (its own bin often looks between two rings)."""
    release_seen_share: float = Field(0.8, ge=0, le=1)
    """The reverse of ``hold_tracks``: a moving instance holding points the mover track
    carried, with no evidence of its own this pair (fewer than ``min_seen_through`` points,
    or 2 % of it, flagged by the network, the geometric or slow-mover tests, or seen
    through), becomes static when the scan ``motion_evidence.baseline_scans`` back (placed
    with the frontend's own poses) saw at least this share of its points in place: a return
    within ``release_margin_m`` of each point's range in the window around its direction
    (the windows with a return must be at least ``release_min_known`` of its points), while
    its motion since that scan would have moved it at least ``release_min_shift_m``. A
    track is a prior: from its start, the ICP of a static bush seen by a few rings of a
    16-beam sensor slides along it at about a walker's speed pair after pair, where the
    older scan sees the bush where it stands and a walker's old place holds something else
    (free space or its old body in front). 0: off. Adopted by rule 21, written before its
    fresh seeds (stop 71): fresh ``static`` 1001-1006 mean share of points dynamic 0.160 ->
    0.116 % (vlp16 1006: 0.556 -> 0.288 %, the rest identical), ``dt`` 1007-1009 identical,
    ``rush-hour`` 1010-1012 identical or better, KITTI and the AV2 pair identical."""
    release_any_prior: bool = False
    """``release_seen_share`` for every moving instance, not only those holding points the
    track carried, with the network's labels counted as a prior like the track, not as
    evidence: only the geometric and slow-mover tests and seen-through points keep an
    instance from being asked. Opt-in: stop 71's rule 22 failed on fresh seeds. Fresh
    ``rush-hour`` 1019-1024 gained instance precision (+0.0022 on average) and EPE3D (1020:
    -1.2 mm), but three seeds had more ID switches (+3.5 to +6.9 per 100 pairs), where the rule
    asked for none more on average."""
    release_margin_m: float = Field(0.2, gt=0)
    """See ``release_seen_share`` (m)."""
    release_min_known: float = Field(0.3, ge=0, le=1)
    """See ``release_seen_share``."""
    release_min_shift_m: float = Field(0.4, ge=0)
    """See ``release_seen_share`` (m): the instance's speed times the time since the older
    scan; at a run's start that scan is only a few scans back. Also for
    ``occupied_release_share`` (since the newest of its older scans)."""
    occupied_release_share: float = Field(0.8, ge=0, le=1)
    """A moving instance wider than a person (its moving points' BEV diagonal over
    ``PERSON_MAX_EXTENT_M``) becomes static when at least this share of its moving points
    clear of the ground lie within ``occupied_radius_m`` of a point of one of the scans
    ``occupied_from_scans`` to ``occupied_to_scans`` before scan k-1 (placed with the
    frontend's own poses), while its motion would have moved it ``release_min_shift_m`` since
    the newest of them, and the older scans prefer that place to the one its own motion gives
    (``occupied_motion_margin``; :func:`flowslam.sceneflow.refinement.occupancy.release_occupied`).
    Unlike ``release_seen_share`` it asks every moving instance, whatever flagged it, and
    several older scans' points instead of one scan's range image: a 16-beam sensor's rings
    cross a parked car at other heights from each viewpoint, so one pair's ICP and free-space
    tests can call it moving, while the older scans together saw it where it stands.
    0: off. Adopted by rule 27, written before its fresh seeds (stop 74): fresh vlp16
    ``static`` 1072 / 1075 0.391 / 1.157 -> 0.350 / 0.286 % of points dynamic (hdl64 and
    vlp32c 1070, 1071, 1073 identical, 1074 0.042 -> 0.036 %), vlp16 ``dt`` 1069 instance
    precision 0.826 -> 0.866 and Dynamic IoU 0.685 -> 0.708, hdl64 ``dt`` 1067 recall
    0.7889 -> 0.7863, ``rush-hour`` 1076-1078 EPE3D within 0.1 mm, KITTI and the AV2 pair
    unchanged or better."""
    occupied_from_scans: int = Field(4, ge=1)
    """See ``occupied_release_share``: the newest older scan asked (scans before scan k-1)."""
    occupied_to_scans: int = Field(8, ge=1)
    """See ``occupied_release_share``: the oldest older scan asked."""
    occupied_radius_m: float = Field(0.2, gt=0)
    """See ``occupied_release_share`` (m)."""
    occupied_motion_margin: float = Field(0.1, ge=0, le=1)
    """See ``occupied_release_share``: the share of those points in place must exceed the
    share the older scans saw where the instance's own motion puts them then (moved back by
    its mean horizontal departure per scan) by at least this: a vehicle driving along its own
    side is seen in place by its own old side (fresh hdl64 ``dt`` 1067: five cars at 3.5-5.4
    m/s released without it, all seen 0.97-1.0 at their moved-back places). Adopted by rule
    28, written before its fresh seeds (stop 74): fresh ``dt`` 1079-1081 recall identical,
    ``rush-hour`` 1088-1090 recall +0.0005 / +0.0006 / 0, vlp16 ``static`` 1087 0.268 -> 0.284 %
    (1084 identical); tuning ``dt`` 1067 recall 0.7863 -> 0.7889."""
    leftover_share: float = Field(0.15, ge=0, le=1)
    """Share of an object's points left unexplained that ``leftover_motion`` registers."""
    own_surface_m: float = Field(0.3, ge=0)
    """A point of a moving object (clear of the ground) whose ego landing lies within this
    (m) of the object's own landings keeps the object's motion even when its ego landing
    is nearer to scan k's surface: a vehicle that slid along itself puts the ego landings
    of its rear onto its own side (simulated `rush-hour` 234: 500-1,000 points of a car
    beside the ego per pair, 0.5-0.8 m of error each). Needs scan k-1's local ground
    (``refine_objects(above_ground=...)``, which the ``ssf`` frontend always passes). 0: off."""
    plane_stage_min_points: int = Field(300, ge=0)
    """... for motions registered on at least this many points (the normals of sparser
    objects are too rough)."""
    grow_max_extent_m: float = Field(8.0, ge=0)
    """After its ICP, a moving object takes the rest of the above-ground BEV components
    (``cluster_cell_m``, at most this BEV diagonal, m) its dynamic points lie in, when its
    motion puts at least ``min_fitness`` of the component on scan k's surface and the ego
    motion clearly less (``static_preference``): the points its motion explains join it
    (the network often flags only part of a vehicle, and a vehicle sliding along itself
    leaves the surface only at its ends). Real AV2 pair: 3-way EPE 0.160 -> 0.074, Dynamic
    IoU 0.27 -> 0.58 (docs/sceneflow_evaluation.md). 0: never."""
    embedded_share: float = Field(0.5, ge=0, le=1.01)
    """A moving object at least this share of whose moving points have another point clear of
    the ground within ``EMBED_RADIUS_M`` (``objects``) lies inside a larger body; when the ego
    motion explains that body's other points (within ``EMBED_BODY_M`` of the object) better
    than the object's motion by ``static_preference``, the object is a part of a static body
    that its ICP slid (real KITTI: a parked car 2.7 m beside the ego, whose flagged lower and
    inner points slid 0.2 m along it while the rest of it fits the ego motion) and stays
    static. 1.01: never."""
    grow_min_seen_through: int = Field(5, ge=0)
    """An object grows only into components holding at least this many seen-through points
    (free space in scan k where they were, ``motion_evidence``): an object of scan k-1
    hidden in scan k also fits some shifted surface by ICP, but scan k does not see
    through it (static preset: the grown false movers were such objects)."""
    grow_movers_from_m: float | None = Field(40.0, ge=0)
    """Beyond this range (horizontal, m) that count also takes the points the
    motion-evidence tests flagged (geometric and slow movers: free space of scan k or of an
    older scan where they are now). An object coming towards the sensor hides its old place
    behind its new one, so scan k sees through none of it: on tuning ``dt`` 1008 a car
    approaching at 75-98 m, found moving at its GT speed in every pair, kept 35-49 % of its
    points (the flagged part) and was missed. Counting them at every range cost tuning ``dt``
    1008 / 1014 0.04 / 0.01 of Dynamic IoU (walkers grown into what they walk along). None: never.
    Adopted by rule 24 with ``motion_evidence.baseline_row_from_m`` (see there)."""
    grow_footprint_cell_m: float = Field(0.3, ge=0)
    """> 0: a moving object also takes the points clear of the ground in its own BEV cells
    of this size (m) that its motion explains better than the ego motion (the growth's
    tests without free space): a walker's legs under its flagged torso. Simulated walkers
    missed for lack of cover had their upper body flagged and their legs not (stop 35).
    Tuning `dt` 241/242/251/252: 0.3 m gives Dynamic IoU +0.012-0.023, instance recall
    -0.003-+0.037, precision up; 0.6 m took a neighbour's points (`dt` 252 recall -0.027);
    letting slow-mover flags count as growth evidence instead cost `dt` 242 0.06 of IoU.
    `static` 243: 0.067 -> 0.073 % of points dynamic. 0: off."""
    max_icp_points: int = Field(1000, ge=10)
    """Points of an object its ICP registers and scores: an evenly strided subset of a
    bigger object (its static score and every point's landing use all its points). Merged
    clusters in dense traffic hold up to 20k points: `rush-hour` 3.2 -> 1.6 s per pair for
    the objects stage with the same flow accuracy (docs/sceneflow_evaluation.md)."""
    margin_m: float = Field(2.0, ge=0)
    """Target points within the box around both the object's predicted and its
    ego-rigid landing spots, grown by this, take part."""
    normal_radius_m: float = Field(1.0, gt=0)
    """Neighbourhood radius (at most 20 points) of the target normals used for scoring."""
    score_distance_m: float = Field(0.3, gt=0)
    """A moved point is on the target surface when its nearest scan-k point is within this ..."""
    score_plane_m: float = Field(0.1, gt=0)
    """... and it is within this of that point's tangent plane."""
    min_fitness: float = Field(0.6, ge=0, le=1)
    """Share of the object's points on the target surface after its ICP."""
    max_rmse_m: float = Field(0.12, gt=0)
    """Largest inlier RMSE of an accepted object ICP."""
    vertical_margin_m: float = Field(0.15, ge=0)
    """A registered motion may move an object's centroid up or down (sensor z of scan k)
    from its ego landing by at most this ..."""
    vertical_grade: float = Field(0.25, ge=0)
    """... plus this times its horizontal departure (a road's grade): objects move on the
    ground, while the ICP of a sparse cluster can slide it up a wall or onto a neighbour
    (held-out ``rush-hour`` 184: 96 objects 0.2-0.7 m up or down, 10 % of the EPE3D,
    docs/sceneflow_evaluation.md). For a sensor mounted tilted, raise both."""
    max_correction_m: float = Field(1.0, gt=0)
    """Objects whose ICP moved their centroid farther than this from the start are
    rejected: sparse clusters can lock onto a shifted copy of the ring pattern."""
    static_preference: float = Field(0.03, ge=0, le=1)
    """An object is static when the ego motion's fitness is within this of its own ICP's
    (or within ``static_preference_sigmas`` standard errors of it, if more) ..."""
    static_preference_sigmas: float = Field(2.0, ge=0)
    """... the standard error of a fitness f measured on n points being sqrt(f (1 - f) / n):
    one point of a 15-point object is 0.067 of fitness, so an ICP that lands one point more
    on scan k's surface than the ego motion is no evidence of motion (real KITTI frames
    0-15: 30 of 151 moving objects, held-out sim `dt` 126: 1 of 71 true movers,
    docs/sceneflow_evaluation.md). 0: the fixed ``static_preference`` alone."""
    static_rmse_ratio: float = Field(1.2, ge=1)
    """... and its inlier RMSE at most this times the ICP's (+ 5 mm) ..."""
    part_rmse_ratio: float = Field(1.0, ge=1)
    """``static_rmse_ratio`` for the parts of a moving object (:func:`flowslam.sceneflow.
    refinement.objects._split_instances`): a part whose ego landings' inlier RMSE exceeds this
    times that of its own landings (+ 5 mm, and above ``static_rmse_floor_m``) keeps moving.
    Slow walkers in a crowd, whose ego landings fit scan k almost as well, were judged static
    at 1.2. Adopted by a rule written before fresh seeds (stop 51): fresh ``rush-hour`` 581 /
    582 instance recall 0.783 / 0.777 -> 0.789 / 0.794, precision 0.924 / 0.928 -> 0.922 /
    0.928; ``dt`` 583 / 584 and ``static`` 585 unchanged within 0.001; real KITTI 0-15
    dynamic points +2 % (docs/sceneflow_evaluation.md)."""
    still_piece_rmse_m: float = Field(0.03, ge=0)
    """A moving part of an object whose points clear of the ground fall into several
    pieces (``instance_cell_m`` BEV components, joined across ``instance_gap_rad``; its low
    points join the piece of their nearest high point) loses
    each piece that the ego motion explains at least as well as the part's motion -- ego
    fitness within the fitness margin of its own, ego inlier RMSE at most its own -- with an
    ego inlier RMSE of at most this (m): such a piece is static. A stopped car in the lane
    beside a passing one, joined to it through low points between them, slides along its
    own sides under the passing car's motion, so its fitness cannot tell; its ego landings
    still fit scan k more tightly (simulated ``rush-hour`` 514: 5,061 such points at 1.4 cm
    against 1.7 cm), while a moving car's pieces scatter 3.4-6 cm under the ego motion.
    0 turns it off. Adopted by a rule written before fresh seeds (stop 55): tuning
    ``rush-hour`` 514 EPE3D 0.0281 -> 0.0261 m, 3-way 0.031 -> 0.017 m; fresh ``rush-hour``
    641 EPE3D 0.0348 -> 0.0344 m, AccStrict +0.5 points, region recall +0.017; fresh 642,
    ``dt`` 643 / 644, ``static`` 645, real KITTI 0-15 and the AV2 pair unchanged
    (docs/sceneflow_evaluation.md)."""
    static_rmse_floor_m: float = Field(0.035, ge=0)
    """... or at most this (m), the spread of a static surface in scan k (as
    ``static_accept_rmse_m``): an ICP with six degrees of freedom lowers the RMSE of a
    small piece of any body a little, which is no evidence of motion (real KITTI 0-15 with
    weights adapted on frames 0-7: a 154-point piece of the parked car beside the ego, RMSE
    3.5 cm under the ego motion against 1.9 cm after ICP, moved at 1 m/s; fresh `dt`
    481-496: mean Dynamic IoU +0.002, docs/sceneflow_evaluation.md, stop 42). 0: off ..."""
    static_fitness_accept: float = Field(0.9, ge=0, le=1.01)
    """... or when the ego motion alone puts this share of its points on scan k's surface
    (no ICP then) ...: a planar patch (road, wall) fits equally well slid along itself, so
    a better ICP fitness there is no evidence of motion ..."""
    static_accept_rmse_m: float = Field(0.035, gt=0)
    """... with an inlier RMSE of at most this (m). A pedestrian walking 0.8 m/s moves 8 cm
    per scan: under the ego motion nearly all its points stay within ``score_plane_m`` of
    scan k, but 4-5 cm off it (static patches of real KITTI scans: median 2.7 cm); such an
    object gets its ICP."""
    static_accept_max_movers: float = Field(0.15, ge=0, le=1.01)
    """... and only when less than this share of its points are geometric movers (scan k
    sees none of its surface where the ego motion puts them): a long vehicle sliding along
    its own side fits its old side plane, so the ego motion scores it as static although
    its ends have left scan k's surface; such an object gets its ICP (held-out
    ``rush-hour`` 184: a bus beside the ego, 24,739 points, 44 % movers, static fitness
    0.92; fresh ``rush-hour`` 234: a car 2.7 m beside the ego, 28,080 points, 27 % movers,
    static fitness 0.93). 0.3 -> 0.15 (stop 31): ``rush-hour`` 234 EPE3D 0.060 -> 0.049,
    ``dt`` 241 Dynamic IoU 0.765 -> 0.790, ``static``, AV2 and KITTI unchanged
    (docs/sceneflow_evaluation.md). > 1: no limit."""
    hidden_static_share: float = Field(1.01, ge=0, le=1.01)
    """Opt-in (> 1: never, the default): an object with no geometric movers and no
    seen-through points (no free space where it was) is static, without an ICP, when at
    least this share of its ego landings lies behind something static of scan k
    (``RangeImage.in_front``, ``hidden_occluder_m``): scan k hides it, so its static fit
    is low for lack of returns, not because it moved. 0.7 takes the simulated ``static``
    scenes from 0.18-0.26 % of points called dynamic to 0.07-0.15 % and leaves
    ``rush-hour`` as it was, but a mover that really goes behind a static occluder is
    made static too (fresh ``dt`` 161 Dynamic IoU 0.604 -> 0.578), so it is off by
    default (docs/sceneflow_evaluation.md)."""
    split_visible: bool = True
    """A part of a moving object with fewer than ``min_seen_through`` seen-through points is
    compared with the ego motion on its visible ego landings only (on scan k's surface, or
    not behind a return away from the part's own landing; as ``visible_static_share``): a
    parked car merged with a car passing between it and the sensor is hidden by that car in
    scan k, so the ego motion fitted it badly and the passing car's slide took it along.
    Measured (stop 31): ``rush-hour`` 234 AccStrict 83.6 -> 86.2 %, the real AV2 pair's
    Dynamic IoU 0.589 -> 0.611, ``dt`` 241 EPE3D 0.0093 -> 0.0097 (docs/sceneflow_evaluation.md).
    False: all its landings count."""
    hidden_occluder_m: float = Field(0.5, ge=0)
    """... counting only the landings hidden by a return farther than this from every
    candidate's input-flow landing (a static occluder, not a walker in front or the
    object's own new surface); 0: any return."""

    visible_static_share: float = Field(0.3, ge=0, le=1.01)
    """An object with no geometric movers and no seen-through points is static, without an
    ICP, when at least this share of its ego landings is visible in scan k (on its
    surface, or not behind a return away from the object's own input-flow landing,
    ``hidden_occluder_m``) and those visible landings alone pass the static acceptance
    (``static_fitness_accept``, ``static_accept_rmse_m``): where the rest landed scan k has
    no return, which is no evidence of motion (> 1: never). Fresh simulated ``static`` 213:
    a parked car half hidden behind a pole was slid along its side at 25 m/s (ego fit 0.58,
    every off-surface landing behind the pole). Measured (stop 31, 0.3): ``static`` 213 /
    233 / 173 0.72 / 0.48 / 0.47 % of points called dynamic -> 0.22 / 0.31 / 0.27 %; the
    real AV2 pair's Dynamic IoU 0.546 -> 0.579; ``dt`` precision up, recall unchanged;
    ``rush-hour`` 234 / 235 one object of ~400 fewer found (docs/sceneflow_evaluation.md)."""
    hidden_rest_free_share: float = Field(0.1, ge=0, le=1.01)
    """A network-dynamic point that no accepted object takes, with no geometric motion
    evidence, also becomes static when scan k hides its ego-rigid landing spot behind a
    return away from its own input-flow landing (``hidden_occluder_m``) and less than this
    share of its BEV cluster (``cluster_cell_m``) lands in view and off scan k's surface,
    where a mover's visible part would have gone (0: never; > 1: whatever its cluster).
    Measured (stop 31, 0.1): fresh ``static`` 213 / 233 / 173 0.22 / 0.31 / 0.27 % of
    points called dynamic -> 0.14 / 0.17 / 0.12 %; the real AV2 pair's Dynamic IoU 0.579
    -> 0.589; ``rush-hour`` 234 EPE3D 0.063 -> 0.060; without the cluster condition
    ``rush-hour`` lost 0.5-1 point of Dynamic IoU (docs/sceneflow_evaluation.md)."""

    @property
    def hidden_test(self) -> bool:
        """Whether a test of hidden ego landings runs (``hidden_static_share`` or
        ``visible_static_share`` at most 1, or ``hidden_rest_free_share`` above 0)."""
        return self.hidden_static_share <= 1 or self.visible_static_share <= 1 or self.hidden_rest_free_share > 0
    track_radius_m: float = Field(0.15, ge=0)
    """Points of the next scan this close to a mover's landing spot become candidates
    (mover tracking; 0: no carry-over)."""
    track_radius_per_m: float = Field(0.0, ge=0)
    """The tracking reach grows with a landing spot's horizontal range d (m), as the beams'
    spacing does: ``clip(track_radius_per_m * d, track_radius_m, track_radius_max_m)`` (rad;
    0: ``track_radius_m`` everywhere). Stop 64, rule 5 (0.03 with ``track_radius_max_m`` 0.6,
    opt-in): fresh `dt` 751 / 752 (100 scans) Dynamic IoU 0.881 / 0.769 -> 0.918 / 0.814,
    all-points instance recall +0.023 / +0.038, region recall +0.013 / +0.021, precision
    not lower; fresh `rush-hour`, `static`, KITTI and the AV2 pair within the rule; but the
    KITTI objects stage 1.057-1.059x slower (rule: 1.05): ~3x the tracked candidates there
    (docs/sceneflow_evaluation.md). Stop 65: with ``track_grow_max_extent_m`` 6 KITTI costs
    1.02-1.04x, but rule 6 missed its mean region-recall gain (0.0097 against 0.01)."""
    track_radius_max_m: float = Field(0.0, ge=0)
    """The largest tracking reach (m) when ``track_radius_per_m`` is set (at most
    ``track_radius_m``: no growth)."""
    track_grow_max_extent_m: float = Field(0.0, ge=0)
    """With ``track_radius_per_m`` set, only the landing spots of objects at most this wide
    (m, the diagonal of the instance's BEV box) get the grown reach; larger objects and
    dynamic points without an instance keep ``track_radius_m`` (0: every landing spot grows).
    Most of KITTI's extra tracked candidates come from objects wider than 6 m (stop 65)."""
    track_max_quiet_pairs: int = Field(0, ge=0)
    """A tracked mover is carried on for at most this many pairs in a row in which its object
    shows no motion of its own: fewer than ``min_seen_through`` (and 2 % of
    its points) flagged by the network, the geometric or slow-mover tests, or seen through
    (:class:`~flowslam.sceneflow.refinement.tracking.MoverPrior`; 0: no limit). Opt-in: stop
    69's rule 16 (1 pair, objects wider than 3 m) failed on fresh seeds. Tuning ``static`` 915
    (vlp16, a bush and a parked car carried on by one track for 9 pairs) fell from 1.57 to
    0.93 % of points dynamic, but fresh ``static`` 931-936 moved 0.999x (clause: 0.97x);
    fresh ``dt`` 939 (vlp16) gained 0.012 Dynamic IoU and 0.019 precision, the others were
    unchanged within 0.001, fresh ``rush-hour`` recall -0.003 at most
    (docs/sceneflow_evaluation.md). Without the width limit, tuning ``dt`` 878 lost 0.028 of
    recall at 2 pairs: real walkers go several pairs without evidence."""
    track_quiet_min_extent_m: float = Field(0.0, ge=0)
    """``track_max_quiet_pairs`` counts only for objects wider than this (m, the diagonal of
    the instance's BEV box; 0: all): a walker moving along the ray leaves no free space to
    see, while a wide body that moves uncovers some."""
    hypotheses_m: list[float] = Field(default_factory=lambda: [-2.0, -1.0, -0.5, 0.5, 1.0, 2.0])
    """Objects with seen-through points also start ICP from the ego landing shifted by
    these distances along their principal (BEV) axis."""
    min_seen_through: int = Field(5, ge=1)
    """Seen-through points an object needs for those extra starts."""
    slide_free_share: float = Field(0.0, ge=0, le=1)
    """> 0: an object wider than a person (``PERSON_MAX_EXTENT_M``) that its ICP leaves
    without a motion of its own, and where the scan ``motion_evidence.baseline_scans`` before
    scan k-1 saw through at least this share of its points clear of the ground, gets the
    slowest slide along its principal axis that puts them back where that scan did not see
    through (:func:`flowslam.sceneflow.refinement.slide.slide_motion`): a vehicle driving
    along its own side, crossing the line of sight, fits scan k under the ego motion as well
    as under its own (tuning `dt` 1014: a car at 35-43 m, 5 m/s, static in 17 pairs with
    35-76 % of its points flagged by the slow-mover test). 0.25 on tuning `dt` 1007 / 1008 /
    1014: all-points recall +0.017 / +0.008 / +0.014, `static` unchanged; rule 26 failed on
    fresh seeds: `dt` 1055-1057 +0.005 / +0.003 / 0 (the clause asked a mean of +0.006), no
    fresh `static` or `rush-hour` seed worse (docs/sceneflow_evaluation.md, stop 73); rule 30 failed
    too: `dt` 1103-1108 mean +0.005, `dt` 1107 EPE3D +0.38 mm from trucks slid at the wrong
    speed (stop 76). 0: off."""
    slide_min_range_m: float = Field(20.0, ge=0)
    """... only objects whose centroid lies at least this far (m, horizontally): nearer, the
    older scan looked from metres away at another angle, and on a 16-beam sensor its rings
    passed over a parked car's roof (tuning `dt` 1039: a parked car at 4 m slid at 4 m/s)."""
    slide_min_rings: int = Field(3, ge=1)
    """... and only objects whose points clear of the ground lie on at least this many of the
    sensor's rings (:func:`~flowslam.sceneflow.refinement.clusters.ring_count`, ``ring_gap_rad``):
    one ring's arc across a fence or a parked car, from a 16-beam sensor 20 m away, is seen
    through by an older scan's rings at other heights and slides (tuning vlp16 ``static`` 1072,
    stop 75, with ``slide_free_share`` 0.25 and far clusters of 8 points: 7 slides of arcs on one
    to three of the sensor's beams, 0.350 -> 0.367 % of points dynamic; with 3 rings none, 0.353 %).
    1: any object."""
    slide_max_free_share: float = Field(0.05, ge=0, le=1)
    """... the share of the object's points a slide may leave in the older scan's free space."""
    slide_step_m: float = Field(0.1, gt=0)
    """... the slides tried: multiples of this (m per scan interval), smallest first."""
    slide_max_step_m: float = Field(2.0, gt=0)
    """... and at most this (m per scan interval: 20 m/s at 10 Hz)."""
    dynamic_speed_mps: float = Field(0.5, ge=0)
    """Objects moving faster than this (relative to the ego-motion flow) are dynamic."""
    horizontal_departure: bool = True
    """A point of an object is moving when its *horizontal* departure from its ego landing
    (sensor frame k, z up) exceeds ``dynamic_speed_mps`` x the scan interval, instead of its
    3D departure: objects move on the ground, and the ICP of a sparse cluster (vegetation,
    a trunk, a pole) slides it a few centimetres up or down. Stop 40: real KITTI 0-15
    ``moving_objects.csv`` 51 -> 46 rows (those gone moved 0.3-0.75 m/s vertically, most of
    their speed); fresh `dt` 422 / 426 (vlp32c) Dynamic IoU 0.728 -> 0.757 / 0.677 -> 0.697,
    precision +0.03 each; 421 / 425 (hdl64), `static` 423 and the tuning seeds unchanged
    within 0.003; fresh `rush-hour` 424 EPE3D 0.0263 -> 0.0264 m, AccStrict 89.65 ->
    89.55 %. For a sensor mounted tilted, turn it off."""
    flat_motion: bool = True
    """Every point left dynamic (objects, held tracks, the network's unregistered movers)
    keeps the height of its ego landing: its flow departs from the ego landing horizontally
    only (sensor frame k, z up). Objects move on the ground, and within one scan interval a
    car at 6 m/s on a 5 % grade rises 3 cm, a walker 0.5 cm; point-to-point ICP of a sparse
    walker, or of a car's sides, slides them up or down along their vertical faces by more
    (simulated `rush-hour` 592, vlp32c: the mean displacement of the objects found was off
    by 3.7-3.8 cm in the median, 1.2-1.7 cm of it horizontally). Adopted by a rule written
    before fresh seeds (stop 52): fresh `rush-hour` 601 / 602 AccStrict 86.3 / 80.6 ->
    87.6 / 88.0 %, EPE3D 0.0347 / 0.0472 -> 0.0324 / 0.0372 m; `dt` 603 / 604 EPE3D -0.5 /
    -0.7 mm; the real AV2 pair 3-way EPE 0.0535 -> 0.0461 m, FD 0.1425 -> 0.1203 m
    (docs/sceneflow_evaluation.md). For a sensor mounted tilted, turn it off."""
    iterations: int = Field(1, ge=1)
    """Cap of the flow <-> segmentation loop (after SSF-PAN's iterative framework): each
    round after the first clusters the points the previous round left dynamic, starts
    every object's ICP from the flow that round gave it, and relabels; 1: one round."""
    converged_share: float = Field(0.005, ge=0, le=1)
    """The loop stops when a round changes the static/dynamic label of at most this share
    of the points dynamic in either round ..."""
    converged_flow_m: float = Field(0.01, ge=0)
    """... and moves the flow of the points dynamic in both rounds by at most this on
    average (m; an object ICP from another start differs by ~1.5 cm at a car's ends)."""
    motion_evidence: MotionEvidenceConfig = MotionEvidenceConfig()
    """Geometric movers added to the candidates."""


class GlobalStartConfig(StrictModel):
    """The global re-initialisation of a faulty step: FPFH + RANSAC (+ ICP) of scan k onto
    scan k-1, no prior needed. The fields below replace the defaults of the ``ransac``
    frontend's options (``ransac:``); the others (feature radii, checkers) keep those defaults."""

    voxel_size_m: float = Field(1.0, gt=0)
    """Voxel of the downsampled clouds that features, RANSAC and ICP work on. 1.0 m (was
    0.5): on five KITTI 64-beam pairs the global start then took 0.33-0.45 s instead of
    1.2-2.2 s and landed 1-6 cm / 0.02-0.11 deg from the reference (0.5 m: 1-2 cm), which
    the stages run again from it refine (docs/motion_recovery.md, stop 57)."""
    max_range_m: float = Field(80.0, gt=0)
    """Points farther than this from the sensor are not used."""
    max_iterations: int = Field(100000, ge=1)
    """RANSAC hypotheses at most."""
    confidence: float = Field(0.999, gt=0, le=1)
    """RANSAC stops once it has found the best hypothesis with this probability."""
    icp_refine: bool = True
    """Refine the RANSAC pose by point-to-plane ICP before it becomes the new start."""
    min_fitness: float = Field(0.3, ge=0, le=1)
    """RANSAC fitness below this: no new start (the step keeps its first solution)."""


class MotionRecoveryConfig(StrictModel):
    """Motion faults: a step whose registration its own evidence does not support is
    re-initialised globally, re-run from the new start, and the better-explained solution
    kept. A step is faulty when any cue below fires (``fallback``: the measurement fell
    back to constant velocity; ``refine_rejected``: the static refinement was rejected;
    ``first_step``, ``fitness_drop``, ``dynamic_jump``, ``prior_disagreement`` as their
    fields say)."""

    enabled: bool = True
    """False: faults are still detected and counted (run.json), nothing is re-run."""
    check_first_step: bool = True
    """Cue ``first_step``: the first step of a sequence is always re-initialised and the
    better-explained solution kept. Its prior is no measurement (zero motion), the relative
    cues have no history yet, and a solution near a wrong zero prior does not disagree with
    it: a sequence that starts at speed is caught here before its first step becomes the
    next prior (stop 48: weights that stayed 2.9 m off on the first steps of the sharp-turn
    sequence end within 4 mm with it; stop 57: the shipped weights left a 10 Hz start with
    1.5 m and 8 deg in its first step 0.82 m / 3.5 deg off, unflagged). Costs one global
    start per sequence (FPFH features of both scans at ``global_start.voxel_size_m`` and
    RANSAC: ~0.3 s on a KITTI 64-beam pair) and, unless the start confirms the step's own
    solution (``confirm_translation_m``), the stages run again (~0.3 s more; 1.7-2.1 s in all
    with the 0.5 m voxel of stops 48-56, when it was off by default)."""
    confirm_translation_m: float = Field(0.1, ge=0)
    """A step whose only cue is ``first_step`` keeps its own solution without running the
    stages again when the global start lies within this translation ..."""
    confirm_rotation_deg: float = Field(0.5, ge=0)
    """... and this rotation of it (outcome ``confirmed``; on a KITTI pair the check then
    takes ~0.3 s instead of ~0.6 s, stop 58). The global start lands 1-6 cm
    and 0.02-0.11 deg from the reference on KITTI pairs; a start at speed that the zero prior
    held back left its solution 0.5-2.9 m away (stops 48, 57). 0: always run them again."""
    fitness_drop: float = Field(0.8, ge=0, le=1)
    """Cue ``fitness_drop``: the refinement's fitness is below this times the median fitness
    of the last good steps."""
    dynamic_jump: float = Field(3.0, ge=1)
    """Cue ``dynamic_jump``: the network calls more of scan k-1 dynamic than this times the
    median share of the last good steps (a wrong ego prior makes static structure look moving) ..."""
    dynamic_share_floor: float = Field(0.05, ge=0, le=1)
    """... and more than this share."""
    history: int = Field(10, ge=1)
    """Good steps whose fitness and dynamic share make the medians above."""
    min_history: int = Field(2, ge=1)
    """The relative cues wait for this many good steps."""
    early_min_fitness: float = Field(0.5, ge=0, le=1)
    """Cue ``early_low_fitness``: while the relative cues wait (fewer than ``min_history``
    good steps), an accepted refinement whose fitness is below this. 0: off. Normal
    sequence starts measured 0.62-0.74 (KITTI, simulated hdl64 / vlp32c, stop 57); a step
    right after a sudden turn at a sequence's start, whose prior carries the turn on,
    refined at 0.31 and ended 0.9 m / 6.8 deg off with no other cue."""
    max_prior_rotation_deg: float = Field(10.0, gt=0)
    """Cue ``prior_disagreement``: the measurement differs from the constant-velocity
    prior by more than this rotation ..."""
    max_prior_translation_m: float = Field(2.0, gt=0)
    """... or by more than this translation."""
    evidence_voxel_m: float = Field(0.3, gt=0)
    """Evidence of a solution: share of scan k's points (voxel-downsampled by this, within
    evidence_max_range_m) that land within evidence_distance_m of a scan k-1 point."""
    evidence_distance_m: float = Field(0.3, gt=0)
    """See evidence_voxel_m."""
    evidence_max_range_m: float = Field(80.0, gt=0)
    """See evidence_voxel_m."""
    min_gain: float = Field(0.02, ge=0, le=1)
    """The re-initialised solution replaces the first when its evidence is higher by this
    (or, when only the first fell back to constant velocity, not lower by this)."""
    global_start: GlobalStartConfig = GlobalStartConfig()
    """The global re-initialisation (FPFH + RANSAC)."""


class SsfConfig(StrictModel):
    """The ``ssf`` frontend: learned scene flow refined at test time, segmentation, odometry."""

    network: NetworkStageConfig = NetworkStageConfig()
    """Stage 1: the learned flow network."""
    pose_start: PoseStartConfig = PoseStartConfig()
    """Stage 2: the refinement's start from the network's static flow."""
    refine: FlowRefinementConfig = FlowRefinementConfig()
    """Stage 3: static refinement against scan k."""
    recovery: MotionRecoveryConfig = MotionRecoveryConfig()
    """Stage 5 (after flow-to-pose): motion-fault detection and global re-initialisation."""
    objects: ObjectRefinementConfig = ObjectRefinementConfig()
    """Stage 6 (after flow-to-pose and recovery): moving objects, instances and their flow."""
    lookahead: bool = True
    """Two threads: the stages before flow-to-pose (network, pose start, static refinement)
    of the next pair (k, k+1) run in a background thread as soon as scan k's pose is
    measured, while the objects stage of pair (k-1, k), the backend, mapping and loop
    closing run. Needs the next scan early: the run loop reads one scan ahead and hands it
    over (``upcoming``). Their inputs are exactly those of the one-thread run, so the
    outputs are the same. False: one thread."""
    early_network: bool = False
    """True: the network places its input scans with scan k's pose from the pose start (the
    network's own static flow, ``T_world_{k-1}`` times the pose start's step) instead of the
    refined pose, so that with ``lookahead`` the network and pose start of pair (k, k+1) run in
    the background while the static refinement of pair (k-1, k) runs in the caller's thread
    (one thread gives the same outputs). The trajectory still composes the refined steps. A
    prior a few centimetres worse for the network; pays where the caller's thread has little
    else to do (``objects.enabled: false``; docs/sceneflow_evaluation.md, stop 76)."""
