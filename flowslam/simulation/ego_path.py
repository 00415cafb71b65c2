"""The ego vehicle's route and motion: block loops in a procedural town, or a given trajectory.

``EgoMotion`` holds:

- ``route``: the polyline the ego vehicle's footprint centre follows (town frame, m);
- ``s_track``: arc length along ``route`` over time (a ``PoseTrack`` abused as
  ``(t, s, 0, 0)``: linear interpolation, held outside the span);
- ``sensor``: the planar pose of the *sensor frame* over time (``PoseTrack``), the
  ground-truth ``T_world_sensor`` (at height ``SensorModel.ground_height``);
- ``frame_times``: the timestamps of the frames (s, first = 0), one more than the
  number of frames written (the flow of the last frame needs the next one).

Procedural towns (``loop_route``): the ego drives clockwise around a block (right
turns only) and around the diagonally opposite block through the same corner,
alternating, so the route keeps coming back to places already seen; the block is
chosen so that one loop fits in the sequence when it can. The speed follows the
curvature (2.5 m/s^2 lateral, 1.5 m/s^2 acceleration, 2 m/s^2 braking), cruising
at ``cruise`` m/s.

Given trajectories (``trajectory_motion``): a KITTI (12 columns) or TUM file. KITTI
ground-truth poses are camera-0 poses (x right, y down, z forward); they are put on
the ground plane as ``X = z_cam, Y = -x_cam``, heading from the camera's optical
axis, height and tilt dropped. A file whose positions vary least along z is taken as
z-up already (``convention`` forces either). The poses' timestamps (a times file,
TUM stamps, or 0.1 s apart) become the frame timestamps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowslam.errors import InputError
from flowslam.simulation.paths import Polyline, PoseTrack, concat_polylines
from flowslam.simulation.roads import RoadNetwork


BEHIND = 60.0
"""Length (m) of route kept behind the ego's start."""


@dataclass
class EgoMotion:
    route: Polyline
    s_track: PoseTrack
    sensor: PoseTrack
    frame_times: np.ndarray
    ego_tracks: set = field(default_factory=set)
    vehicle_center_x: float = 0.0
    description: str = ""
    oncoming_route: Polyline | None = None
    """Procedural loops: the ego's loops driven the other way (the oncoming lanes), for a
    scripted stream of oncoming vehicles; ``oncoming_s`` is arc length over time along it."""
    oncoming_s: PoseTrack | None = None

    def s_at(self, t) -> np.ndarray:
        return self.s_track.at(t)[0]

    def footprint_at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ego vehicle footprint centre x, y and heading at time(s) t."""
        x, y, yaw = self.sensor.at(t)
        return x + self.vehicle_center_x * np.cos(yaw), y + self.vehicle_center_x * np.sin(yaw), yaw


def speed_profile(line: Polyline, cruise: float, v_start: float | None = None, lateral_accel: float = 2.5,
                  accel: float = 1.5, decel: float = 2.0) -> np.ndarray:
    """Speed (m/s) at each vertex of ``line``: curvature limit, then braking/acceleration passes."""
    k = line.curvature()
    if len(k) > 9:
        k = np.convolve(np.pad(k, 4, mode="edge"), np.ones(9) / 9, mode="valid")
    v = np.minimum(cruise, np.sqrt(lateral_accel / np.maximum(k, 1e-6)))
    ds = np.diff(line.s)
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * decel * ds[i]))
    v[0] = min(v[0], cruise if v_start is None else v_start)
    for i in range(len(v) - 1):
        v[i + 1] = min(v[i + 1], np.sqrt(v[i] ** 2 + 2 * accel * ds[i]))
    return np.maximum(v, 0.5)


def _time_param(line: Polyline, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ds = np.diff(line.s)
    dt = 2 * ds / (v[:-1] + v[1:])
    return np.concatenate([[0.0], np.cumsum(dt)]), line.s


def _lane_of(net: RoadNetwork, a: int, b: int) -> int:
    for e, (u, v) in enumerate(net.node_of_edge):
        if (u, v) == (a, b):
            return net.lane_ids[(e, 1)]
        if (u, v) == (b, a):
            return net.lane_ids[(e, -1)]
    raise KeyError((a, b))


def _connector(net: RoadNetwork, lane_in: int, lane_out: int) -> int:
    for c in net.tracks[lane_in].next:
        if net.tracks[c].next == [lane_out]:
            return c
    raise KeyError((lane_in, lane_out))


def _cell_cycle(nx: int, i: int, j: int) -> list[int]:
    """Clockwise node cycle around grid cell (i, j), starting at its lower-left node."""
    idx = lambda a, b: b * nx + a  # noqa: E731
    return [idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)]


def loop_route(net: RoadNetwork, grid_shape: tuple[int, int], rng: np.random.Generator, frames: int,
               frame_period: float, cruise: float, vehicle_center_x: float, extra_time: float) -> EgoMotion:
    """Block loops through one corner node (module doc)."""
    nx, ny = grid_shape
    duration = frames * frame_period
    distance = 0.6 * cruise * duration  # the ego slows down for the corners
    best = None
    for i in range(nx - 1):
        for j in range(ny - 1):
            cyc = _cell_cycle(nx, i, j)
            perim = sum(np.linalg.norm(net.nodes[cyc[k]] - net.nodes[cyc[(k + 1) % 4]]) for k in range(4))
            central = (1 <= i < nx - 2 or nx <= 3) and (1 <= j < ny - 2 or ny <= 3)
            fits = (perim - 25.0) * 1.15 <= distance  # lanes cut the corners: ~25 m shorter
            key = (fits, central, perim if fits else -perim, rng.random())
            if best is None or key > best[0]:
                best = (key, i, j)
    _, i, j = best
    cycle_a = _cell_cycle(nx, i, j)  # starts at node (i, j)
    corner = cycle_a[0]
    # diagonal cell through the same corner: (i-1, j-1), traversed starting at its node (i, j)
    cycles = [cycle_a]
    if i >= 1 and j >= 1:
        cb = _cell_cycle(nx, i - 1, j - 1)
        k = cb.index(corner)
        cycles.append(cb[k:] + cb[:k])
    # lanes of one pass through the cycles, as node pairs
    node_seq = []
    for cyc in cycles:
        node_seq += cyc
    node_seq_closed = node_seq + [node_seq[0]]
    lanes = [_lane_of(net, a, b) for a, b in zip(node_seq_closed[:-1], node_seq_closed[1:])]
    # route: start half-way along the lane that enters the corner (the last of the first
    # loop), so that the first completed loop already comes back to the start; then the
    # loops in turn, lanes joined by connectors
    need = cruise * (duration + extra_time) + 200.0
    first = lanes[len(cycle_a) - 1]
    pieces = [net.tracks[first].line]
    start_s = 0.5 * pieces[0].length
    ego_tracks = {first}
    total = pieces[0].length - start_s
    k = 0
    prev = first
    while total < need:
        b = lanes[k % len(lanes)]
        con = _connector(net, prev, b)
        ego_tracks.update((b, con))
        pieces += [net.tracks[con].line, net.tracks[b].line]
        total += net.tracks[con].line.length + net.tracks[b].line.length
        prev = b
        k += 1
    # the same loops the other way round: the oncoming lanes, reserved for a scripted stream
    rev_nodes = node_seq_closed[::-1]
    rev_lanes = [_lane_of(net, a, b) for a, b in zip(rev_nodes[:-1], rev_nodes[1:])]
    rev_pieces = [net.tracks[rev_lanes[0]].line]
    rev_total = rev_pieces[0].length
    k = 0
    while rev_total < need + 2 * cruise * 60.0:
        a, b = rev_lanes[k % len(rev_lanes)], rev_lanes[(k + 1) % len(rev_lanes)]
        con = _connector(net, a, b)
        ego_tracks.update((a, b, con))
        rev_pieces += [net.tracks[con].line, net.tracks[b].line]
        rev_total += net.tracks[con].line.length + net.tracks[b].line.length
        k += 1
    for t in ego_tracks:
        net.tracks[t].ego = True
    # the route starts at the beginning of the first lane (room behind the ego for a
    # following convoy vehicle); the ego is at start_s at time 0
    route = concat_polylines(pieces).resampled(0.5)
    v = speed_profile(route, cruise)
    times, s = _time_param(route, v)
    times = times - np.interp(start_s, s, times)
    motion = _motion_from_route(route, times, s, frames, frame_period, vehicle_center_x)
    motion.ego_tracks = ego_tracks
    motion.description = f"block loop(s) around {len(cycles)} block(s), cruise {cruise:.1f} m/s"
    rev = concat_polylines(rev_pieces).resampled(0.5)
    rt, rs = _time_param(rev, speed_profile(rev, cruise))
    # start so that 60 s of stream lie before time 0 (vehicles at t - i * headway exist)
    motion.oncoming_route = rev
    motion.oncoming_s = PoseTrack(rt - 60.0, rs, np.zeros_like(rs), np.zeros_like(rs))
    return motion


def _motion_from_route(route, times, s, frames, frame_period, vehicle_center_x, dt=0.02) -> EgoMotion:
    s_track = PoseTrack(times, s, np.zeros_like(s), np.zeros_like(s))
    tg = np.arange(np.ceil(times[0] / dt) * dt, times[-1], dt)
    sg = s_track.at(tg)[0]
    pos = route.position(sg)
    yaw = route.heading(sg)
    sensor = PoseTrack(tg, pos[:, 0] - vehicle_center_x * np.cos(yaw), pos[:, 1] - vehicle_center_x * np.sin(yaw), yaw)
    frame_times = np.arange(frames + 1) * frame_period
    return EgoMotion(route, s_track, sensor, frame_times, vehicle_center_x=vehicle_center_x)


# ------------------------------------------------------------------ given trajectories
def read_ground_path(path: str | Path, times_path: str | Path | None = None, convention: str = "auto",
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(times, x, y, yaw) of a trajectory file put on the ground plane (module doc)."""
    from flowslam.trajectory import read_trajectory

    path = Path(path)
    traj = read_trajectory(path)
    if len(traj) < 2:
        raise InputError(path, "needs at least 2 poses")
    P = traj.poses
    pos = P[:, :3, 3]
    if convention == "auto":
        convention = "kitti-camera" if np.argmin(pos.std(axis=0)) == 1 else "z-up"
    if convention == "kitti-camera":
        x, y = pos[:, 2], -pos[:, 0]
        yaw = np.arctan2(-P[:, 0, 2], P[:, 2, 2])
    elif convention == "z-up":
        x, y = pos[:, 0], pos[:, 1]
        yaw = np.arctan2(P[:, 1, 0], P[:, 0, 0])
    else:
        raise InputError(path, f"unknown trajectory convention {convention!r} (auto, kitti-camera, z-up)")
    if times_path is not None:
        from flowslam.datasets.scan_files import read_times_file

        times = read_times_file(Path(times_path), expected=len(P))
    elif traj.timestamps is not None:
        times = traj.timestamps
    else:
        times = np.arange(len(P)) * 0.1
    times = np.asarray(times, dtype=np.float64) - float(times[0])
    if np.any(np.diff(times) <= 0):
        raise InputError(times_path or path, "timestamps must increase")
    return times, x, y, np.unwrap(yaw)


def trajectory_motion(times, x, y, yaw, frames: int | None, vehicle_center_x: float, first: int = 0
                      ) -> EgoMotion:
    """Ego motion along given sensor poses: frames are the poses ``first .. first+frames-1``."""
    n_avail = len(times) - first
    if frames is None:
        frames = n_avail - 1
    if frames < 1 or frames > n_avail - 1:
        raise InputError(None, f"the trajectory has {len(times)} poses: from pose {first} at most {n_avail - 1} "
                               f"frames (each frame's flow needs the next pose), not {frames}")
    # the poses of the frames (+1 for the last flow), and up to 100 more for the route ahead
    sl = slice(first, min(first + frames + 101, len(times)))
    t = np.asarray(times[sl], dtype=np.float64)
    px, py, pyaw = np.asarray(x[sl]), np.asarray(y[sl]), np.unwrap(np.asarray(yaw[sl]))
    t = t - t[0]
    frame_times = t[: frames + 1]
    # beyond the last pose: constant velocity (the last sweep and the route ahead need it)
    dt = t[-1] - t[-2]
    k = np.arange(1, 41)
    t_ext = np.concatenate([t, t[-1] + k * dt])
    x_ext = np.concatenate([px, px[-1] + k * (px[-1] - px[-2])])
    y_ext = np.concatenate([py, py[-1] + k * (py[-1] - py[-2])])
    yaw_ext = np.concatenate([pyaw, pyaw[-1] + k * (pyaw[-1] - pyaw[-2])])
    sensor = PoseTrack(t_ext, x_ext, y_ext, yaw_ext)
    cx = x_ext + vehicle_center_x * np.cos(yaw_ext)
    cy = y_ext + vehicle_center_x * np.sin(yaw_ext)
    seg = np.hypot(np.diff(cx), np.diff(cy))
    # the route polyline: footprint centres (dropping repeated points where the car stands),
    # with a straight lead-in of BEHIND metres (room for a following convoy vehicle)
    keep = np.concatenate([[True], seg > 1e-3])
    pts = np.column_stack([cx, cy])[keep]
    h0 = yaw_ext[0]
    lead_in = pts[0] - np.arange(BEHIND, 0, -1.0)[:, None] * np.array([np.cos(h0), np.sin(h0)])
    h1 = yaw_ext[-1]
    lead_out = pts[-1] + np.arange(1.0, BEHIND + 1)[:, None] * np.array([np.cos(h1), np.sin(h1)])
    route = Polyline(np.concatenate([lead_in, pts, lead_out]))
    s = BEHIND + np.concatenate([[0.0], np.cumsum(np.where(keep[1:], seg, 0.0))])
    s_track = PoseTrack(t_ext, s, np.zeros_like(s), np.zeros_like(s))
    return EgoMotion(route, s_track, sensor, frame_times, vehicle_center_x=vehicle_center_x,
                     description=f"given trajectory, {frames} frames")


# ------------------------------------------------------------------ sharp turns at a low frame rate
SHARP_TURNS_DEG = (0.0, 0.0, 40.0, 0.0, -30.0, -30.0, 0.0, 25.0, 45.0, 0.0, -20.0, 0.0)
"""Yaw change per frame (deg) of :func:`write_sharp_turn_path`'s default: turns of 20-45 deg
per frame, each after a straight step or another turn, so the constant-velocity prior
is off by up to 45 deg at every change."""


def sharp_turn_poses(yaw_steps_deg=SHARP_TURNS_DEG, step_m: float = 3.0, period_s: float = 0.5
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Planar z-up poses ``T_world_sensor`` (N+1, 4, 4) and their times (N+1,) (s) of a
    path that moves ``step_m`` per frame (along the mean heading of the step) and turns
    by ``yaw_steps_deg[k]`` (deg) in step k, frames ``period_s`` apart (0.5 s: 2 Hz)."""
    from flowslam import geometry

    yaw = np.concatenate([[0.0], np.cumsum(np.deg2rad(np.asarray(yaw_steps_deg, dtype=np.float64)))])
    mid = 0.5 * (yaw[:-1] + yaw[1:])
    xy = np.vstack([[0.0, 0.0], np.cumsum(step_m * np.column_stack([np.cos(mid), np.sin(mid)]), axis=0)])
    poses = np.stack([geometry.make_T(geometry.from_euler("z", h)[:3, :3], [x, y, 0.0])
                      for (x, y), h in zip(xy, yaw)])
    return poses, np.arange(len(poses)) * period_s


def write_sharp_turn_path(path: str | Path, yaw_steps_deg=SHARP_TURNS_DEG, step_m: float = 3.0,
                          period_s: float = 0.5) -> Path:
    """Write :func:`sharp_turn_poses` as a TUM file (a ``--trajectory`` for the simulator:
    ``len(yaw_steps_deg)`` frames, each with its successor for the flow)."""
    from flowslam.trajectory import Trajectory, write_tum

    poses, times = sharp_turn_poses(yaw_steps_deg, step_m, period_s)
    write_tum(path, Trajectory(poses, times))
    return Path(path)
