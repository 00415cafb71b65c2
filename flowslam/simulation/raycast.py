"""Ray casting one LiDAR sweep against the static town and the moving actors (Open3D/Embree).

The static town is one ``RaycastingScene`` built once (the ground plane z = 0 is
intersected analytically). The actor shapes sit side by side in a second scene (the
"atlas"), built once in their local frames; an actor is hit by casting the rays
*transformed into its local frame at each ray's firing time*, so actors can move
during the sweep without rebuilding anything. Rays are culled per actor by an
azimuth/elevation window and a bounding-sphere test, then all actors' rays are cast
in one call. The nearest hit (ground, static or actor) wins.

Timing: with ``distortion`` each column fires at ``t0 + tau_c`` (``SensorModel``),
and the sensor pose and every actor pose are taken at that instant; without it the
whole sweep is taken at ``t0`` (an instantaneous scan).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowslam.simulation.actors import ActorSet
from flowslam.simulation.paths import PoseTrack
from flowslam.simulation.sensors import SensorModel
from flowslam.simulation.town import StaticWorld


@dataclass
class RawScan:
    """The rays that hit something (before noise, dropout and range limits)."""

    ray: np.ndarray
    """Flat ray index ``column * B + beam``."""
    column: np.ndarray
    beam: np.ndarray
    t: np.ndarray
    """Hit distance along the unit ray (m, float64 of Embree's float32)."""
    actor: np.ndarray
    """Index into ``ActorSet.actors`` of the actor hit, -1 for the static world."""
    label: np.ndarray
    """Static hits: the triangle's instance label (-1 = ground); actors: their instance id."""
    cos_incidence: np.ndarray
    column_times: np.ndarray
    """(C,) firing time offsets used (zeros without distortion)."""


def _scene(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


def _cast(scene, rays: np.ndarray):
    import open3d as o3d

    out = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
    return out["t_hit"].numpy(), out["primitive_ids"].numpy(), out["primitive_normals"].numpy()


ATLAS_SPACING = 25.0
"""Distance (m) between the actor shapes in the atlas scene: more than twice any shape's
bounding radius, small enough to keep float32 coordinates precise."""


class Raycaster:
    def __init__(self, world: StaticWorld, actors: ActorSet, sensor: SensorModel):
        self.world = world
        self.actors = actors
        self.sensor = sensor
        # the ground plane z = 0 is intersected analytically (exact, and a huge triangle slows
        # Embree's traversal down); everything else goes into one scene
        objects = world.mesh.labels >= 0
        self.tri_label = world.mesh.labels[objects]
        self.static_scene = _scene(world.mesh.vertices, world.mesh.triangles[objects])
        self.dirs = sensor.ray_directions()  # (C, B, 3) float64, sensor frame
        self.flat_dirs = self.dirs.reshape(-1, 3)
        self._dirs32 = self.dirs.astype(np.float32)
        elev, head, self.offsets, spin, phase = sensor.beam_table()
        self.elevation = elev
        self.head_of_beam = head
        self.spin = spin
        self.phase = phase
        self.C, self.B = self.dirs.shape[:2]
        self.tau = sensor.column_times()
        self._dirs64z = self.flat_dirs[:, 2].copy()  # planar motion: z of a direction never changes
        self._origin_z = np.tile(sensor.ground_height + self.offsets[:, 2], self.C)
        self._heads = []
        for h in np.unique(head):
            beams = np.flatnonzero(head == h)
            self._heads.append((beams, spin[beams[0]], phase[beams[0]], sensor.ground_height + self.offsets[beams[0], 2]))
        # all actor tracks side by side, for culling them all at once
        acts = actors.actors
        S = len(actors.times)
        self._X = np.array([a.track.x for a in acts]).reshape(len(acts), S)
        self._Y = np.array([a.track.y for a in acts]).reshape(len(acts), S)
        self._alive = np.array([a.alive for a in acts], dtype=bool).reshape(len(acts), S)
        self._radius = np.array([actors.shapes[a.shape].radius for a in acts])
        self._height = np.array([actors.shapes[a.shape].height for a in acts])
        self._shape_radius = [s.radius for s in actors.shapes]
        self._actor_ids = np.array([a.id for a in acts], dtype=np.int64)
        self._YAW = np.array([a.track.yaw for a in acts]).reshape(len(acts), S)
        shape_idx = np.array([a.shape for a in acts], dtype=np.int64)
        self._radius_shape_of_actor = np.array(self._shape_radius)[shape_idx] if len(acts) else np.zeros(0)
        # elevations of each head, sorted ascending, with the beam index of each
        self._head_sorted = {}
        for beams, *_ in self._heads:
            order = beams[np.argsort(self.elevation[beams], kind="stable")]
            self._head_sorted[int(beams[0])] = (self.elevation[order], order)
        # the atlas: every shape once, ATLAS_SPACING apart along x, in one scene
        spacing = ATLAS_SPACING
        self._atlas_x = (np.arange(len(actors.shapes)) - (len(actors.shapes) - 1) / 2) * spacing
        verts, tris, off = [], [], 0
        for j, shape in enumerate(actors.shapes):
            verts.append(shape.mesh.vertices + [self._atlas_x[j], 0.0, 0.0])
            tris.append(shape.mesh.triangles + off)
            off += len(shape.mesh.vertices)
        self.atlas = _scene(np.concatenate(verts), np.concatenate(tris)) if verts else None
        self._atlas_x_of_actor = self._atlas_x[shape_idx] if len(acts) else np.zeros(0)

    def _actor_xy(self, t: float):
        times = self.actors.times
        dt = times[1] - times[0]
        u = np.clip((t - times[0]) / dt, 0, len(times) - 1)
        i = min(int(np.floor(u)), len(times) - 2)
        f = u - i
        return (self._X[:, i] + f * (self._X[:, i + 1] - self._X[:, i]),
                self._Y[:, i] + f * (self._Y[:, i + 1] - self._Y[:, i]))

    def world_rays(self, ex, ey, eyaw) -> np.ndarray:
        """(C, B, 6) float32 rays (origin, unit direction) in the town frame for per-column
        sensor poses ``ex, ey, eyaw`` (C,)."""
        c = np.cos(eyaw).astype(np.float32)[:, None]
        s = np.sin(eyaw).astype(np.float32)[:, None]
        D = self._dirs32
        rays = np.empty((self.C, self.B, 6), dtype=np.float32)
        rays[..., 3] = c * D[..., 0] - s * D[..., 1]
        rays[..., 4] = s * D[..., 0] + c * D[..., 1]
        rays[..., 5] = D[..., 2]
        O = self.offsets
        rays[..., 0] = (ex[:, None] + np.cos(eyaw)[:, None] * O[None, :, 0] - np.sin(eyaw)[:, None] * O[None, :, 1])
        rays[..., 1] = (ey[:, None] + np.sin(eyaw)[:, None] * O[None, :, 0] + np.cos(eyaw)[:, None] * O[None, :, 1])
        rays[..., 2] = (self.sensor.ground_height + O[:, 2])[None, :]
        return rays

    def cast(self, t0: float, ego: PoseTrack, distortion: bool) -> RawScan:
        sensor = self.sensor
        tau = self.tau if distortion else np.zeros(self.C)
        ex, ey, eyaw = ego.at(t0 + tau)
        rays = self.world_rays(ex, ey, eyaw).reshape(-1, 6)
        t_hit, prim, normals = _cast(self.static_scene, rays)
        best = t_hit.astype(np.float64)
        label = self.tri_label[np.minimum(prim, len(self.tri_label) - 1)]
        cosi = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:]))
        # the ground: t = height / -dz for rays going down
        dz = self._dirs64z
        with np.errstate(divide="ignore"):
            t_ground = np.where(dz < 0, self._origin_z / -np.minimum(dz, -1e-12), np.inf)
        g = t_ground < best
        best[g] = t_ground[g]
        label[g] = -1
        cosi[g] = -dz[g]
        best[best > sensor.max_range + 1.0] = np.inf
        hit_actor = np.full(best.shape, -1, dtype=np.int64)
        self._cast_actors(t0, tau, ex, ey, eyaw, rays, best, hit_actor, label, cosi)
        valid = np.flatnonzero(np.isfinite(best))
        return RawScan(
            ray=valid, column=valid // self.B, beam=valid % self.B, t=best[valid], actor=hit_actor[valid],
            label=label[valid], cos_incidence=cosi[valid], column_times=tau,
        )

    # ------------------------------------------------------------------ actors
    def _cast_actors(self, t0, tau, ex, ey, eyaw, rays, best, hit_actor, label, cosi) -> None:
        """All actors' candidate rays, in their local frames, cast at once against the atlas
        of shapes (shapes ATLAS_SPACING apart along x; each ray starts where it enters its
        actor's bounding sphere and counts only inside it, so atlas neighbours never
        interfere). Candidates: per actor and head, the columns around its azimuth and the
        beams around its elevation, then a bounding-sphere test; all vectorised."""
        actors = self.actors
        sensor = self.sensor
        T = sensor.sweep_period
        if len(actors.actors) == 0:
            return
        times = actors.times
        dt = times[1] - times[0]
        i0 = int(np.clip(np.round((t0 - times[0]) / dt), 0, len(times) - 1))
        mid = len(ex) // 2
        ego_turn = float(np.abs(eyaw[-1] - eyaw[0]))
        ego_step = float(np.hypot(ex[-1] - ex[0], ey[-1] - ey[0]))
        x0, y0 = self._actor_xy(t0)
        x1, y1 = self._actor_xy(t0 + T / 2)
        x2, y2 = self._actor_xy(t0 + T)
        rx, ry = x1 - ex[mid], y1 - ey[mid]
        rho = np.hypot(rx, ry)
        margin = self._radius + np.hypot(x2 - x0, y2 - y0) + ego_step + 0.3
        cand = np.flatnonzero(self._alive[:, i0] & (rho - margin <= sensor.max_range))
        if len(cand) == 0:
            return
        C, B = self.C, self.B
        # actor poses at each column's firing time: interpolation indices per column
        u = np.clip((t0 + tau - times[0]) / dt, 0, len(times) - 1)
        ci = np.minimum(np.floor(u).astype(np.int64), len(times) - 2)
        cf = u - ci
        rk, mk = rho[cand], margin[cand]
        near = rk <= mk + 0.5
        half = np.where(near, np.pi, np.arcsin(np.minimum(1.0, mk / np.maximum(rk, 1e-9))) + ego_turn + 2 * np.pi / C)
        az = np.arctan2(ry[cand], rx[cand]) - eyaw[mid]
        width = np.minimum(np.ceil(half / (2 * np.pi) * C).astype(np.int64) + 1, C)
        half_el = np.where(near, np.pi, np.arcsin(np.minimum(1.0, mk / np.maximum(rk, 1e-9))) + 0.02)
        zc = self._height[cand] / 2
        idx_l, k_l = [], []
        for beams, spin, phase, z_head in self._heads:
            el_sorted, order = self._head_sorted[int(beams[0])]
            el = np.arctan2(zc - z_head, rk)
            b_lo = np.searchsorted(el_sorted, el - half_el, side="left")
            b_hi = np.searchsorted(el_sorted, el + half_el, side="right")
            c_center = np.round((np.pi + phase - az) / (2 * np.pi) * C * spin).astype(np.int64)
            full = 2 * width + 1 >= C
            c_start = np.where(full, 0, c_center - width)
            n_cols = np.where(full, C, 2 * width + 1)
            n_beams = np.maximum(b_hi - b_lo, 0)
            counts = n_cols * n_beams
            ok = counts > 0
            if not ok.any():
                continue
            kk = np.repeat(np.arange(len(cand))[ok], counts[ok])
            starts = np.repeat(np.cumsum(counts[ok]) - counts[ok], counts[ok])
            j = np.arange(len(kk)) - starts
            col = np.mod(c_start[kk] + j // n_beams[kk], C)
            beam = order[b_lo[kk] + j % n_beams[kk]]
            idx_l.append(col * B + beam)
            k_l.append(kk)
        if not idx_l:
            return
        idx = np.concatenate(idx_l)
        kk = np.concatenate(k_l)
        k_actor = cand[kk]
        col = idx // B
        i_c, f_c = ci[col], cf[col]
        px = self._X[k_actor, i_c] + f_c * (self._X[k_actor, i_c + 1] - self._X[k_actor, i_c])
        py = self._Y[k_actor, i_c] + f_c * (self._Y[k_actor, i_c + 1] - self._Y[k_actor, i_c])
        R = rays[idx]
        r = self._radius_shape_of_actor[k_actor]
        wx, wy, wz = px - R[:, 0], py - R[:, 1], zc[kk] - R[:, 2]
        tp = wx * R[:, 3] + wy * R[:, 4] + wz * R[:, 5]
        d2 = wx * wx + wy * wy + wz * wz - tp * tp
        keep = (d2 < r * r) & (tp > -r) & (tp - r < best[idx])
        if not keep.any():
            return
        idx, R, tp, r, k_actor, px, py = idx[keep], R[keep], tp[keep], r[keep], k_actor[keep], px[keep], py[keep]
        i_c, f_c = i_c[keep], f_c[keep]
        yaw = self._YAW[k_actor, i_c] + f_c * (self._YAW[k_actor, i_c + 1] - self._YAW[k_actor, i_c])
        c, s = np.cos(yaw), np.sin(yaw)
        # start each ray where it enters the bounding sphere: nothing of the atlas lies
        # between, and the float32 coordinates stay small
        t_start = np.maximum(tp - r, 0.0)
        ox = R[:, 0] + t_start * R[:, 3] - px
        oy = R[:, 1] + t_start * R[:, 4] - py
        local = np.empty((len(idx), 6), dtype=np.float32)
        local[:, 0] = c * ox + s * oy + self._atlas_x_of_actor[k_actor]
        local[:, 1] = -s * ox + c * oy
        local[:, 2] = R[:, 2] + t_start * R[:, 5]
        local[:, 3] = c * R[:, 3] + s * R[:, 4]
        local[:, 4] = -s * R[:, 3] + c * R[:, 4]
        local[:, 5] = R[:, 5]
        t_hit, _, normals = _cast(self.atlas, local)
        t_rel = t_hit.astype(np.float64)
        ok = t_rel <= tp + r - t_start + 0.01
        t_abs = t_rel + t_start
        ok &= t_abs < best[idx]
        if not ok.any():
            return
        idx, t_abs, k_actor = idx[ok], t_abs[ok], k_actor[ok]
        cos_ok = np.abs(np.einsum("ij,ij->i", normals[ok], local[ok, 3:]))
        # the nearest actor hit of each ray
        order = np.lexsort((t_abs, idx))
        idx, t_abs, k_actor, cos_ok = idx[order], t_abs[order], k_actor[order], cos_ok[order]
        first = np.concatenate([[True], idx[1:] != idx[:-1]])
        idx, t_abs, k_actor, cos_ok = idx[first], t_abs[first], k_actor[first], cos_ok[first]
        best[idx] = t_abs
        hit_actor[idx] = k_actor
        label[idx] = self._actor_ids[k_actor]
        cosi[idx] = cos_ok
