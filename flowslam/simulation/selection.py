"""Choosing which simulated actors to keep so that a sequence has a target number of
dynamic points per frame (the ``dh`` / ``dt`` presets).

Traffic is simulated with more actors than needed; a quick *pilot* render (the
reference sensor at a quarter of its columns, every few frames) counts how many
rays each actor takes while it moves. A greedy search then keeps the subset whose
per-frame sums are closest (least squares) to the target, always keeping the scripted
vehicles (convoy, oncoming stream). The others are removed from the whole sequence (removing actors never
creates a collision). The pilot always uses ``REFERENCE_SENSOR``, so a preset and
seed give the same scene whatever sensor observes it.
"""

from __future__ import annotations

import numpy as np

REFERENCE_SENSOR = "hdl64"
REFERENCE_COLUMNS = 2048
PILOT_COLUMNS = 512


def pilot_counts(world, actors, ego, max_pilot_frames: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """(A, F) rays on each moving actor per pilot frame (scaled to the reference sensor), and
    the pilot frame indices."""
    from flowslam.simulation.raycast import Raycaster
    from flowslam.simulation.sensors import get_sensor

    sensor = get_sensor(REFERENCE_SENSOR, columns=PILOT_COLUMNS)
    caster = Raycaster(world, actors, sensor)
    n = len(ego.frame_times) - 1
    frames = np.unique(np.linspace(0, n - 1, min(n, max_pilot_frames)).round().astype(int))
    A = len(actors.actors)
    counts = np.zeros((A, len(frames)))
    scale = REFERENCE_COLUMNS / PILOT_COLUMNS
    for j, k in enumerate(frames):
        t0, t1 = float(ego.frame_times[k]), float(ego.frame_times[k + 1])
        raw = caster.cast(t0, ego.sensor, False)
        hit = raw.actor[raw.actor >= 0]
        c = np.bincount(hit, minlength=A).astype(np.float64)
        # only while the actor moves faster than the dynamic threshold
        for k_a in np.flatnonzero(c):
            x, y, _ = actors.actors[k_a].track.at(np.array([t0, t1]))
            if np.hypot(x[1] - x[0], y[1] - y[0]) <= 0.5 * (t1 - t0):
                c[k_a] = 0.0
        counts[:, j] = c * scale
    return counts, frames


def choose(counts: np.ndarray, target: float, keep: np.ndarray) -> np.ndarray:
    """Greedy least squares: a boolean mask of actors whose summed counts per frame stay
    closest to ``target``; actors in ``keep`` are always in."""
    chosen = keep.copy()
    total = counts[chosen].sum(axis=0)
    sq = (counts**2).sum(axis=1)
    while True:
        delta = 2.0 * counts @ (total - target) + sq
        delta[chosen] = np.inf
        delta[counts.sum(axis=1) == 0] = np.inf
        k = int(np.argmin(delta)) if len(delta) else -1
        if k < 0 or not np.isfinite(delta[k]) or delta[k] >= 0:
            return chosen
        chosen[k] = True
        total += counts[k]


def select_actors(world, actors, ego, target: float) -> dict:
    """Keep (in place) the actors that bring the dynamic points per frame close to ``target``."""
    if not actors.actors:
        return {"target": target, "candidates": 0, "kept": 0}
    counts, frames = pilot_counts(world, actors, ego)
    keep = np.array([a.kind in ("convoy", "oncoming") for a in actors.actors])
    chosen = choose(counts, target, keep)
    n_before = len(actors.actors)
    actors.actors[:] = [a for a, c in zip(actors.actors, chosen) if c]
    est = counts[chosen].sum(axis=0)
    return {"target": float(target), "candidates": n_before, "kept": int(chosen.sum()),
            "pilot_mean": float(est.mean()) if len(est) else 0.0}
