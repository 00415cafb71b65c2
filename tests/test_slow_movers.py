"""Slow movers: free space in an older scan where a point of scan k-1 is now.

A walker moving 15 cm per scan never leaves scan k's surface in one step (the off-surface
test needs 25 cm), but three scans earlier the sensor saw the wall behind the place where
the walker now stands. Built with exact geometry (surfaces sampled densely enough that
every range-image bin has returns); the ego vehicle moves, and the older scan is placed
with the frontend's own poses."""

import numpy as np

from flowslam import geometry
from flowslam.config import SsfConfig
from flowslam.config.ssf import MotionEvidenceConfig
from flowslam.flow_odometry import FlowPoseEstimate
from flowslam.frame import Frame
from flowslam.sceneflow.refinement.visibility import RangeImage, slow_movers

HEIGHT = 1.73
STEP = 0.8  # ego motion per scan, forward (m)


def _grid(lo, hi, step=0.03) -> np.ndarray:
    """Points on an axis-aligned box face or plane from ``lo`` to ``hi`` (one of the three
    extents zero), every ``step`` metres."""
    axes = [np.arange(a, b + 1e-9, step) if b > a else np.array([a]) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _box(centre_xy, size=(0.4, 0.4, 1.6)) -> np.ndarray:
    """The four vertical faces of a box standing on the ground (world frame, m)."""
    (cx, cy), (sx, sy, sz) = centre_xy, size
    z0, z1 = -HEIGHT + 0.05, -HEIGHT + sz
    return np.concatenate([
        _grid((cx - sx / 2, cy - sy / 2, z0), (cx - sx / 2, cy + sy / 2, z1)),
        _grid((cx + sx / 2, cy - sy / 2, z0), (cx + sx / 2, cy + sy / 2, z1)),
        _grid((cx - sx / 2, cy - sy / 2, z0), (cx + sx / 2, cy - sy / 2, z1)),
        _grid((cx - sx / 2, cy + sy / 2, z0), (cx + sx / 2, cy + sy / 2, z1)),
    ])


def _world(walker_y: float) -> np.ndarray:
    """World points (world = the older scan's sensor frame): a wall 14 m ahead, a pillar, the
    walker at (10, walker_y), the ground."""
    wall = _grid((14.0, -4.0, -HEIGHT), (14.0, 4.0, 1.0))
    ground = _grid((-4.0, -5.0, -HEIGHT), (16.0, 5.0, -HEIGHT), step=0.25)
    return np.concatenate([wall, _box((10.0, -2.0)), _box((10.0, walker_y)), ground])


def _scan(world: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
    return geometry.transform_points(geometry.inv(T_world_sensor), world)


def _pose(k: int) -> np.ndarray:
    return geometry.from_euler("z", 0.0, t=[STEP * k, 0.0, 0.0])


def _walker_mask(points_world: np.ndarray, walker_y: float) -> np.ndarray:
    return (np.abs(points_world[:, 0] - 10.0) <= 0.21) & (np.abs(points_world[:, 1] - walker_y) <= 0.21) \
        & (points_world[:, 2] > -HEIGHT + 0.01)


def test_a_walker_has_left_the_free_space_of_an_older_scan():
    """The walker moved 0.45 m in three scans: where it stands now, scan k-4 saw the wall.
    The pillar, the wall and the ground stood there then too."""
    c = MotionEvidenceConfig()
    y_old, y_now = 1.45, 1.0  # 15 cm per scan, sideways
    old = _scan(_world(y_old), _pose(0))
    now_world = _world(y_now)
    prev = _scan(now_world, _pose(3))  # scan k-1, three scans later
    T_old_prev = geometry.inv(_pose(0)) @ _pose(3)
    flagged = slow_movers(prev, T_old_prev, RangeImage(old, c), c)
    walker = _walker_mask(now_world, y_now)
    assert flagged[walker].mean() > 0.5
    assert not flagged[~walker].any()  # wall, pillar, ground: all seen there before

    # the walker standing still (only the ego vehicle moved): nothing is flagged
    still = _scan(_world(y_now), _pose(0))
    assert not slow_movers(prev, T_old_prev, RangeImage(still, c), c).any()
    # the evidence is where the points stand, not where they were: the walker's old place
    # (free in scan k-1) does not flag the older scan's points
    back = slow_movers(old, geometry.inv(T_old_prev), RangeImage(prev, c), c)
    assert not back[_walker_mask(_world(y_old), y_old)].all()


def _pair(frames: list, poses: list, k: int, window: int):
    """The objects stage's state of the pair (k-1, k) with a window of ``window`` scans
    ending with k-1, scan k measured at its true pose."""
    from frontends.ssf_stages import PairState

    state = PairState(frames[k - 1], frames[k], frames[k - window:k], poses[k - window:k], T_world_guess=poses[k])
    T_prev_curr = geometry.inv(poses[k - 1]) @ poses[k]
    state.estimate = FlowPoseEstimate(T_prev_curr, np.eye(6), geometry.inv(T_prev_curr),
                                      np.ones(len(frames[k - 1].points), dtype=bool), False, None)
    return state


def _stage_slow_movers(stage, state, image) -> np.ndarray:
    """The slow movers as ``ObjectsStage.run`` finds them: scan k's range ``image`` kept, the
    older scan looked up once, the test against it (no shared ground)."""
    stage._keep_image(state, image)
    return stage._slow_movers(state, None, stage._older_view(state))


def test_the_objects_stage_tests_the_scan_baseline_scans_older_in_its_window():
    """``ObjectsStage`` takes the older scan from the network's window and places it with the
    frontend's own poses; ``baseline_scans: 0`` turns the test off, and a window shorter than
    the baseline uses its oldest scan."""
    from frontends.ssf_stages import ObjectsStage

    ys = [1.45, 1.3, 1.15, 1.0, 0.85]  # the walker at scans k-4 .. k
    frames = [Frame(index=i, timestamp=0.1 * i, points=_scan(_world(y), _pose(i))) for i, y in enumerate(ys)]
    poses = [_pose(i) for i in range(5)]
    walker = _walker_mask(_world(ys[3]), ys[3])

    def flagged(baseline: int, window: int) -> np.ndarray:
        config = SsfConfig()
        config.objects.motion_evidence.baseline_scans = baseline
        stage = ObjectsStage(config)
        image = RangeImage(frames[4].points, config.objects.motion_evidence)
        return _stage_slow_movers(stage, _pair(frames, poses, 4, window), image)

    assert flagged(3, 4)[walker].mean() > 0.5  # against scan k-4: 45 cm of free space
    assert not flagged(0, 4).any()
    assert flagged(3, 2)[walker].any()  # window of two: scan k-2 (15 cm; the window still sees through part)
    assert not flagged(3, 1).any()  # no scan older than k-1 in the window


def test_the_objects_stage_reaches_beyond_the_window_with_the_images_and_poses_it_kept():
    """A walker at 5 cm per scan, a window of four scans, ``baseline_scans: 8``: the stage
    has seen scans 1-10 as scan k and tests scan 9 against scan 1 (its range image and own
    pose as kept then, 40 cm of free space), exactly as :func:`slow_movers` against scan 1
    does; against the window's oldest scan (k-4, 15 cm) fewer walker points are flagged."""
    from frontends.ssf_stages import ObjectsStage

    ys = [1.6 - 0.05 * i for i in range(11)]
    frames = [Frame(index=i, timestamp=0.1 * i, points=_scan(_world(y), _pose(i))) for i, y in enumerate(ys)]
    poses = [_pose(i) for i in range(11)]
    walker = _walker_mask(_world(ys[9]), ys[9])

    def flagged(baseline: int) -> np.ndarray:
        config = SsfConfig()
        config.objects.motion_evidence.baseline_scans = baseline
        config.objects.motion_evidence.long_baseline_scans = 0  # the images of this baseline alone
        stage = ObjectsStage(config)
        for k in range(1, 11):
            image = RangeImage(frames[k].points, config.objects.motion_evidence)
            out = _stage_slow_movers(stage, _pair(frames, poses, k, min(k, 4)), image)
        assert len(stage._images) <= baseline + 2  # only what the baseline needs is kept
        return out

    c = SsfConfig().objects.motion_evidence
    direct = slow_movers(frames[9].points, geometry.inv(poses[1]) @ poses[9], RangeImage(frames[1].points, c), c,
                         source_image=RangeImage(frames[9].points, c))
    far = flagged(8)
    assert np.array_equal(far, direct)
    assert far[walker].mean() > 0.5 and not far[~walker].any()
    assert flagged(3)[walker].mean() < far[walker].mean()


def _behind_box(points: np.ndarray, lo, hi) -> np.ndarray:
    """(N,) bool: the segment from the sensor (origin) to each point passes through the box
    ``lo``-``hi`` before reaching it (a ray cast: such a point is not in the scan)."""
    d = np.where(np.abs(points) < 1e-12, 1e-12, points)
    t0, t1 = (np.asarray(lo) - 0.0) / d, (np.asarray(hi) - 0.0) / d
    enter = np.minimum(t0, t1).max(axis=1)
    leave = np.maximum(t0, t1).min(axis=1)
    return (enter <= leave) & (enter > 0) & (enter < 1.0 - 1e-6)


def _walker_on_axis(x: float, wall_x: float, post_x: float, ground_to: float) -> tuple[np.ndarray, np.ndarray]:
    """A standing sensor's scan (its frame, m), ray-cast from the origin: a wall across at
    ``wall_x``, a post at (``post_x``, -2), the ground up to ``ground_to`` and a walker at
    (``x``, 0), with the walker's mask."""
    walker = _box((x, 0.0))
    rest = np.concatenate([_grid((wall_x, -4.0, -HEIGHT), (wall_x, 4.0, 1.0)), _box((post_x, -2.0)),
                           _grid((-4.0, -5.0, -HEIGHT), (ground_to, 5.0, -HEIGHT), step=0.25)])
    rest = rest[~_behind_box(rest, walker.min(axis=0), walker.max(axis=0))]
    return np.concatenate([rest, walker]), np.arange(len(rest) + len(walker)) >= len(rest)


def test_a_walker_walking_away_leaves_the_place_in_front_of_where_it_is_now():
    """The walker walks straight away from a standing sensor, 0.7 m in seven scans: the older
    scan saw its old body in front of where it is now (no free space there), and scan k-1
    sees through that old body's place. ``baseline_vacated`` flags it; the wall and ground
    behind it (now seen, then hidden), the pillar and the rest stay unflagged, and nothing
    is flagged without the option or without scan k-1's range image."""
    old, _ = _walker_on_axis(9.3, wall_x=14.0, post_x=10.0, ground_to=16.0)
    prev, walker = _walker_on_axis(10.0, wall_x=14.0, post_x=10.0, ground_to=16.0)
    c = MotionEvidenceConfig(baseline_vacated=True)
    flagged = slow_movers(prev, np.eye(4), RangeImage(old, c), c, source_image=RangeImage(prev, c))
    assert flagged[walker].mean() > 0.5
    assert not flagged[~walker].any()
    assert not slow_movers(prev, np.eye(4), RangeImage(old, c), c).any()  # no scan k-1 image
    plain = MotionEvidenceConfig(baseline_vacated=False)
    assert not slow_movers(prev, np.eye(4), RangeImage(old, plain), plain, source_image=RangeImage(prev, plain)).any()


def test_the_own_bin_test_ignores_a_return_in_front_in_the_neighbouring_bin():
    """A range image with a wall at 10 m and, one azimuth bin to the left, a post at 5 m: a
    point at 8 m in the wall's direction has only returns beyond it in its own bin, but the
    post in front inside its 3x3 window. The window test (scan k's seen-through, and the
    default slow-mover test) says no; the own-bin test (``baseline_own_bin``) says yes,
    with its smaller margins, and no again within those margins of the wall."""
    c = MotionEvidenceConfig()
    az0 = 0.2 * c.azimuth_resolution_deg  # inside one azimuth bin ...
    el = np.radians(np.arange(-3.0, 3.01, 0.1))

    def ray(az_deg, r):
        az = np.radians(az_deg)
        return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)

    image = RangeImage(np.concatenate([ray(az0, 10.0), ray(az0 + c.azimuth_resolution_deg, 5.0)]), c)  # ... and the next
    own = dict(own_bin=True, margin_m=c.baseline_margin_m, relative_margin=c.baseline_relative_margin)
    point = ray(az0, 8.0)[30:31]  # elevation 0
    assert not image.sees_beyond(point)[0]
    assert image.sees_beyond(point, **own)[0]
    assert not image.sees_beyond(ray(az0, 9.8)[30:31], **own)[0]  # 9.8 + 0.15 + 0.098 > 10


def test_the_opt_in_own_bin_slow_test_finds_more_of_the_walker():
    """On the walker scene, ``baseline_own_bin`` flags more of the walker than the default
    test (its points next to the old body's bins) and still none of the wall, pillar or
    ground. (Not a superset: a point whose own bin holds no return is unknown there.)"""
    y_old, y_now = 1.45, 1.0
    old = _scan(_world(y_old), _pose(0))
    now_world = _world(y_now)
    prev = _scan(now_world, _pose(3))
    T_old_prev = geometry.inv(_pose(0)) @ _pose(3)
    default = MotionEvidenceConfig()
    loose = MotionEvidenceConfig(baseline_own_bin=True)
    a = slow_movers(prev, T_old_prev, RangeImage(old, default), default)
    b = slow_movers(prev, T_old_prev, RangeImage(old, loose), loose)
    walker = _walker_mask(now_world, y_now)
    assert b[walker].sum() > 1.1 * a[walker].sum() > 0
    assert not b[~walker].any()


def test_a_walker_walking_towards_the_sensor_is_within_the_old_relative_margin_but_not_the_new():
    """A walker 25 m ahead of a standing sensor comes 0.6 m nearer over the baseline: along
    its rays the older scan saw its old body 0.6 m behind where it is now. The seen-through
    test's margins (0.3 m + 2 % of 25 m = 0.8 m) call that no free space; the slow-mover
    test's own relative margin (``baseline_window_relative_margin`` 0.005: 0.3 + 0.125 m)
    does. The wall behind, the ground and the post beside it stay unflagged either way."""
    old, _ = _walker_on_axis(25.6, wall_x=30.0, post_x=25.0, ground_to=31.0)
    prev, walker = _walker_on_axis(25.0, wall_x=30.0, post_x=25.0, ground_to=31.0)
    flagged = {}
    for name, relative in (("old", None), ("new", 0.005)):
        c = MotionEvidenceConfig(baseline_window_relative_margin=relative, baseline_vacated=False)
        flagged[name] = slow_movers(prev, np.eye(4), RangeImage(old, c), c)
    # the face towards the sensor (the box's other faces are not ray-cast), clear of the ground
    front = walker & (prev[:, 0] < 24.81) & (prev[:, 2] > -HEIGHT + 0.35)
    assert not flagged["old"].any()
    assert flagged["new"][front].mean() > 0.9 and not flagged["new"][~walker].any()


def test_a_far_walker_walking_away_is_within_the_vacated_window_margins_only():
    """A walker 24 m ahead of a standing sensor walks 0.7 m away over the baseline: the older
    scan saw its old body 0.7 m in front of where it is now. The seen-through test's margins
    (0.3 m + 2 % of 24 m = 0.78 m) call that nothing in front, so the vacated test (stop 34)
    misses it; with ``baseline_vacated_window_from_m`` (10 m) it uses the windowed test's
    margins there (0.3 + 0.5 % = 0.42 m) and flags the walker. The wall behind it, the post
    beside it and the ground stay unflagged either way, and so does the same walker 7 m
    ahead, where the wider margins stay (0.3 m + 2 % of 7 m = 0.44 m > its 0.4 m walk)."""
    def flagged(near: float, step: float, window_from):
        old, _ = _walker_on_axis(near - step, wall_x=near + 5.0, post_x=near, ground_to=near + 6.0)
        prev, walker = _walker_on_axis(near, wall_x=near + 5.0, post_x=near, ground_to=near + 6.0)
        c = MotionEvidenceConfig(baseline_vacated_window_from_m=window_from)
        return slow_movers(prev, np.eye(4), RangeImage(old, c), c, source_image=RangeImage(prev, c)), walker

    before, walker = flagged(24.0, 0.7, None)
    after, _ = flagged(24.0, 0.7, 10.0)
    assert not before[walker].any() and not before[~walker].any()
    assert after[walker].mean() > 0.5 and not after[~walker].any()
    near, walker = flagged(7.0, 0.4, 10.0)
    assert not near.any()
    everywhere, _ = flagged(7.0, 0.4, 0.0)  # the window's margins there too would flag it
    assert everywhere[walker].mean() > 0.5


def test_a_long_baseline_finds_a_walker_the_short_one_misses_once_the_run_reaches_it():
    """A walker at 4 cm per scan, ``baseline_scans: 3`` (12 cm, within its own width) and
    ``long_baseline_scans: 12``: until the stage has kept the image of the scan 12 before scan
    k-1 (seen as scan k; the run's scan 0 never is) the long test gives nothing; from then on it
    flags the walker (48 cm of free space), exactly as :func:`slow_movers` against that scan,
    and nothing else; points nearer than ``long_baseline_from_m`` are never flagged by it."""
    from frontends.ssf_stages import ObjectsStage

    n = 17
    ys = [1.6 - 0.04 * i for i in range(n)]
    poses = [geometry.from_euler("z", 0.0, t=[0.2 * i, 0.0, 0.0]) for i in range(n)]
    frames = [Frame(index=i, timestamp=0.1 * i, points=_scan(_world(y), poses[i])) for i, y in enumerate(ys)]

    def run(from_m: float) -> tuple[list, list]:
        config = SsfConfig()
        evidence = config.objects.motion_evidence
        evidence.baseline_scans, evidence.long_baseline_scans, evidence.long_baseline_from_m = 3, 12, from_m
        stage = ObjectsStage(config)
        short, long = [], []
        for k in range(1, n):
            state = _pair(frames, poses, k, min(k, 4))
            short.append(_stage_slow_movers(stage, state, RangeImage(frames[k].points, evidence)))
            long.append(stage._long_slow_movers(state, None))
        assert len(stage._images) <= 12 + 2  # only what the longer baseline needs is kept
        return short, long  # [k - 1]: scan k-1's flags

    short, long = run(0.0)
    assert all(flags is None for flags in long[:13])  # k = 1..13: scan k-13 not kept
    c = SsfConfig().objects.motion_evidence
    for k in (14, 15, 16):
        walker = _walker_mask(_world(ys[k - 1]), ys[k - 1])
        direct = slow_movers(frames[k - 1].points, geometry.inv(poses[k - 13]) @ poses[k - 1],
                             RangeImage(frames[k - 13].points, c), c, source_image=RangeImage(frames[k - 1].points, c))
        assert np.array_equal(long[k - 1], direct)
        assert long[k - 1][walker].mean() > 0.5 and not long[k - 1][~walker].any()
        assert short[k - 1][walker].mean() < 0.5 * long[k - 1][walker].mean()
    _, far_only = run(8.0)  # the walker stands ~7 m from the sensor
    assert all(flags is None for flags in far_only[:13]) and not any(flags.any() for flags in far_only[13:])


def test_where_the_older_scan_was_hidden_a_newer_one_tests_the_slow_mover():
    """A standing sensor; a walker at (10, y) steps 12 cm sideways per scan; 7 scans before
    scan k-1 a box at 5 m stood on the line of sight to where the walker is now, then left.
    That older scan did not see the walker's place (:func:`hidden_points`), so the 7-scan test
    finds nothing there; with ``hidden_baseline_scans: 4`` the scan 4 back, which saw the wall
    behind that place, flags the walker and nothing else."""
    from frontends.ssf_stages import ObjectsStage
    from flowslam.sceneflow.refinement.visibility import hidden_points

    n, prev = 11, 9
    ys = [2.2 - 0.12 * t for t in range(n)]
    wall = _grid((14.0, -4.0, -HEIGHT), (14.0, 4.0, 1.0))
    ground = _grid((-4.0, -5.0, -HEIGHT), (16.0, 5.0, -HEIGHT), step=0.25)

    def scan(t: int) -> np.ndarray:
        occluder = (5.0, ys[prev] / 2 + 3.0 * (t - 2))  # on the line of sight at t = 2, then gone
        size = (0.4, 0.8, 1.8)
        box = _box(occluder, size)
        rest = np.concatenate([wall, ground, _box((10.0, ys[t]))])
        lo = (occluder[0] - size[0] / 2, occluder[1] - size[1] / 2, -HEIGHT + 0.05)
        hi = (occluder[0] + size[0] / 2, occluder[1] + size[1] / 2, -HEIGHT + size[2])
        return np.concatenate([rest[~_behind_box(rest, lo, hi)], box])

    frames = [Frame(index=t, timestamp=0.1 * t, points=scan(t)) for t in range(n)]
    poses = [np.eye(4)] * n
    walker = _walker_mask(frames[prev].points, ys[prev])

    def run(hidden_back: int) -> tuple[np.ndarray, np.ndarray]:
        config = SsfConfig()
        evidence = config.objects.motion_evidence
        evidence.baseline_scans, evidence.hidden_baseline_scans, evidence.long_baseline_scans = 7, hidden_back, 0
        stage = ObjectsStage(config)
        for k in range(1, prev + 2):
            state = _pair(frames, poses, k, min(k, 4))
            short = _stage_slow_movers(stage, state, RangeImage(frames[k].points, evidence))
            extra = stage._hidden_slow_movers(state, None, stage._older_view(state))
        return short, extra

    c = SsfConfig().objects.motion_evidence
    hidden = hidden_points(frames[prev].points, np.eye(4), RangeImage(frames[prev - 7].points, c), c)
    assert hidden[walker].mean() > 0.5
    short, none = run(0)
    assert short[walker].mean() < 0.2 and not none.any()
    short, extra = run(4)
    assert extra[walker].mean() > 0.5 and not extra[~walker].any()
