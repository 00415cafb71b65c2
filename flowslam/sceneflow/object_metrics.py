"""Moving-object metrics (small pure functions and one accumulator): instance recall and
precision, speed and velocity error of the objects found, ID switches.

Definitions (per scan pair; points of scan k-1):

- a **GT object** is a GT instance with at least ``min_points`` GT-dynamic points; a
  **predicted object** is a predicted instance with at least ``min_points`` points the
  method calls dynamic;
- a GT object is **found** when one predicted instance (of any size) covers at least
  ``min_cover`` of its points with an IoU of at least ``min_iou`` (point sets; the
  instance with the largest overlap is the candidate). **Recall** = found / GT objects;
  **precision** = predicted objects that found a GT object / predicted objects (an
  instance under ``min_points`` may find a GT object but is not a predicted object: a
  50-point walker covered by a 45-point instance is found, and no fragment of a few
  points counts against precision);
- for a found object, the **speed error** is ``| |v| - |v_gt| |`` and the **velocity
  error** ``|v - v_gt|`` (m/s), each velocity the mean ego-compensated flow of the
  object's dynamic points / dt (:func:`flowslam.moving_objects.moving_objects`; the
  method's with its own flow and ego motion, GT's with GT flow and poses);
- an **ID switch**: a GT object found in a pair by a predicted object whose track id
  differs from the track id that found it the last time it was found; reported per 100
  scan pairs;
- **why a GT object is missed** (:func:`miss_reasons`), one reason each: *unflagged*
  (fewer than ``min_cover`` of its points are called dynamic), *split* (enough are, but
  no one instance covers ``min_cover`` of them: it is in pieces), *merged* (one instance
  covers it but its IoU is under ``min_iou``: the instance also holds other points, e.g.
  a neighbour). Reported as counts beside recall.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ObjectScores", "match_instances", "miss_reasons", "MISS_REASONS"]

MISS_REASONS = ("unflagged", "split", "merged")
"""The reasons :func:`miss_reasons` gives, in the order of its test."""


def match_instances(pred: np.ndarray, gt: np.ndarray, min_points: int = 50, min_cover: float = 0.5,
                    min_iou: float = 0.5) -> tuple[dict[int, int], list[int], list[int]]:
    """Found GT objects of one pair (module doc): {GT id: predicted instance id}, the GT
    objects and the predicted objects (ids with at least ``min_points`` points). ``pred``, ``gt``: (N,)
    int instance ids per point, -1 for none (static points already set to -1)."""
    pred, gt = np.asarray(pred, np.int64), np.asarray(gt, np.int64)
    gt_ids, gt_counts = np.unique(gt[gt >= 0], return_counts=True)
    pred_ids, pred_counts = np.unique(pred[pred >= 0], return_counts=True)
    gt_objects = [int(g) for g in gt_ids[gt_counts >= min_points]]
    pred_objects = [int(p) for p in pred_ids[pred_counts >= min_points]]
    gt_size, pred_size = dict(zip(gt_ids.tolist(), gt_counts.tolist())), dict(zip(pred_ids.tolist(), pred_counts.tolist()))
    both = (gt >= 0) & (pred >= 0)
    pairs, overlap = np.unique(np.stack([gt[both], pred[both]], axis=1).reshape(-1, 2), axis=0, return_counts=True)
    best: dict[int, tuple[int, int]] = {}  # GT id -> (overlap, predicted id) of the largest overlap
    for (g, p), n in zip(pairs.tolist(), overlap.tolist()):
        if n > best.get(g, (0, -1))[0]:
            best[g] = (n, p)
    found: dict[int, int] = {}
    for g in gt_objects:
        if g not in best:
            continue
        n, p = best[g]
        if n / gt_size[g] >= min_cover and n / (gt_size[g] + pred_size[p] - n) >= min_iou:
            found[g] = p
    return found, gt_objects, pred_objects


def miss_reasons(pred: np.ndarray, gt: np.ndarray, found: dict[int, int], gt_objects: list[int],
                 min_cover: float = 0.5) -> dict[int, str]:
    """{GT id: reason} for each GT object of ``gt_objects`` not in ``found`` (module doc:
    ``unflagged``, ``split`` or ``merged``); ``pred``, ``gt`` as for :func:`match_instances`."""
    pred, gt = np.asarray(pred, np.int64), np.asarray(gt, np.int64)
    out: dict[int, str] = {}
    for g in gt_objects:
        if g in found:
            continue
        mine = pred[gt == g]
        flagged = mine[mine >= 0]
        if flagged.size == 0 or flagged.size < min_cover * mine.size:
            out[g] = "unflagged"
        elif np.bincount(flagged - flagged.min()).max() < min_cover * mine.size:
            out[g] = "split"
        else:
            out[g] = "merged"
    return out


class ObjectScores:
    """Accumulates the module's metrics over the pairs of a run."""

    def __init__(self, min_points: int = 50, min_cover: float = 0.5, min_iou: float = 0.5):
        self.rule = dict(min_points=min_points, min_cover=min_cover, min_iou=min_iou)
        self.gt_objects = self.found = self.pred_objects = self.true_pred = self.switches = self.pairs = 0
        self.speed_errors: list[float] = []
        self.velocity_errors: list[float] = []
        self._last_track: dict[int, int] = {}
        self.missed = dict.fromkeys(MISS_REASONS, 0)

    def add(self, pred: np.ndarray, gt: np.ndarray, velocity: dict[int, np.ndarray],
            gt_velocity: dict[int, np.ndarray], track: dict[int, int]) -> None:
        """One pair: per-point ids (``match_instances``), the predicted and GT velocities by
        id (m/s, the same frame), the predicted objects' track ids by id (absent: untracked)."""
        found, gt_objects, pred_objects = match_instances(pred, gt, **self.rule)
        self.pairs += 1
        self.gt_objects += len(gt_objects)
        self.found += len(found)
        self.pred_objects += len(pred_objects)
        self.true_pred += len(set(found.values()) & set(pred_objects))
        for reason in miss_reasons(pred, gt, found, gt_objects, self.rule["min_cover"]).values():
            self.missed[reason] += 1
        for g, p in found.items():
            if p in velocity and g in gt_velocity:
                v, v_gt = np.asarray(velocity[p]), np.asarray(gt_velocity[g])
                self.speed_errors.append(abs(float(np.linalg.norm(v) - np.linalg.norm(v_gt))))
                self.velocity_errors.append(float(np.linalg.norm(v - v_gt)))
            if p in track:
                if g in self._last_track and self._last_track[g] != track[p]:
                    self.switches += 1
                self._last_track[g] = track[p]

    def result(self) -> dict:
        """JSON-serialisable metrics (None where nothing was there to count)."""
        def ratio(a: int, b: int):
            return a / b if b else None

        def median(x: list[float]):
            return float(np.median(x)) if x else None

        return {
            "gt_objects": self.gt_objects, "predicted_objects": self.pred_objects, "found": self.found,
            "recall": ratio(self.found, self.gt_objects), "precision": ratio(self.true_pred, self.pred_objects),
            "median_speed_error_mps": median(self.speed_errors),
            "median_velocity_error_mps": median(self.velocity_errors),
            "id_switches_per_100_pairs": ratio(100 * self.switches, self.pairs),
            **{f"missed_{reason}": n for reason, n in self.missed.items()}, **self.rule,
        }
