"""How the adapted weights compare with the starting ones on the held-out tails.

Each set of weights runs as the network-only ``ssf`` frontend (``ssf.refine.enabled:
false``: the network's flow and segmentation, flow-to-pose odometry, no test-time
refinement) through the same frame loop as ``flowslam run`` (``run_pipeline``, odometry
backend) from a few scans before the held-out tail (``Sequence.scoring_frames``), so
that the held-out scans get the history and the own poses of a continuous run; only
the held-out pairs (both scans in the tail, which training never saw) are scored.
Measured per sequence:

- without labels: ``data_term_m``, the mean distance of each warped point of scan
  k-1 (``p + flow``) to its nearest point of scan k (capped at ``adapt.truncate_m``);
  ``teacher_epe_m``, the mean end-point error against the refined pipeline's flow;
  ``teacher_dynamic_iou``, the dynamic IoU against the teacher's segmentation;
- with ground truth, where the reader has it: ``rpe1_trans_m`` (RPE over one frame,
  translation RMSE against the GT poses) and, with GT flow, the ``flow-eval`` metrics
  (``EPE3D``, ``DynamicIoU``, ...) under ``gt_flow``.

Then, with ``adapt.report_refined``, each set of weights also runs in the whole default
``ssf`` frontend (test-time refinement and objects) over the same frames, which shows
what the weights change where they are used: the same measures (against the teacher
they are ~0 for the starting weights, which made it), and what the frontend spends per
held-out pair: ``frame_ms_median`` (all stages), ``objects_ms_median`` (the objects
stage), ``object_candidates_mean`` (points handed to it), ``objects_mean`` (objects it
registered), ``dynamic_points_mean`` (points it left dynamic). A network that flags
fewer false candidates makes the objects stage cheaper.

Lengths in metres, times in milliseconds (wall time of this process).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowslam.config import PipelineConfig
from flowslam.frame import Frame
from flowslam.interfaces import FrontendOutput


class _SelfSupervisedScores:
    """Output sink: the label-free measures of the module doc, over the pairs it sees."""

    def __init__(self, teacher, truncate_m: float, scored: set[int]):
        self.teacher = teacher
        self.scored = scored
        self.truncate_m = truncate_m
        self._prev: Frame | None = None
        self.data: list[float] = []
        self.epe: list[np.ndarray] = []
        self.pred_dyn: list[np.ndarray] = []
        self.teacher_dyn: list[np.ndarray] = []

    def on_output(self, frame: Frame, out: FrontendOutput) -> None:
        import torch

        from flowslam.sceneflow.network.self_supervised import chamfer_to_scan

        prev, self._prev = self._prev, frame
        if prev is None or out.flow is None or frame.index not in self.scored:
            return
        self.data.append(float(chamfer_to_scan(torch.from_numpy(out.points + out.flow), frame.points, self.truncate_m)))
        pair = self.teacher.pairs.get(frame.index)
        if pair is not None and len(pair.flow) == len(out.flow):
            self.epe.append(np.linalg.norm(out.flow - pair.flow, axis=1))
            static = np.ones(len(out.flow), bool) if out.static_mask is None else np.asarray(out.static_mask, bool)
            self.pred_dyn.append(~static)
            self.teacher_dyn.append(~pair.static)

    def result(self) -> dict:
        from flowslam.sceneflow.metrics import dynamic_iou

        if not self.data:
            return {}
        out = {"data_term_m": float(np.mean(self.data))}
        if self.epe:
            out["teacher_epe_m"] = float(np.mean(np.concatenate(self.epe)))
            out["teacher_dynamic_iou"] = dynamic_iou(np.concatenate(self.pred_dyn), np.concatenate(self.teacher_dyn))
        return out


def with_weights(config: PipelineConfig, weights: Path) -> PipelineConfig:
    """``config`` with these network weights (the default, refined ``ssf`` otherwise)."""
    config = config.model_copy(deep=True)
    config.ssf.network.weights = Path(weights)
    return config


def network_only(config: PipelineConfig, weights: Path) -> PipelineConfig:
    """``config`` with the network-only ``ssf`` (no refinement) and these weights."""
    config = with_weights(config, weights)
    config.ssf.refine.enabled = False
    return config


def _frontend_costs(stats: list[dict], rows: list[int]) -> dict:
    """What the frontend spent on the pairs ``rows`` of a run's ``frontend_stats``."""
    picked = [stats[r] for r in rows]
    laps = [s["stage_ms"] for s in picked if "stage_ms" in s]

    def summary(reduce, values: list) -> float:
        return float(reduce(values)) if values else float("nan")

    def mean(key: str) -> float:
        return summary(np.mean, [s[key] for s in picked if key in s])

    return {"frame_ms_median": summary(np.median, [sum(lap.values()) for lap in laps]),
            "objects_ms_median": summary(np.median, [lap["objects"] for lap in laps if "objects" in lap]),
            "object_candidates_mean": mean("object_candidates"), "objects_mean": mean("objects"),
            "dynamic_points_mean": mean("dynamic_points")}


def score_weights(sequence, config: PipelineConfig, weights: Path, num_frames: int, refined: bool = False) -> dict:
    """The module doc's measures of network-only ``ssf`` (``refined``: the default ``ssf``
    of ``config``, plus its costs per pair) with ``weights`` on the held-out pairs of
    ``sequence`` (a ``loop.Sequence`` with its teacher); ``num_frames``: the network's
    input scans (the run starts that many scans before the tail)."""
    from flowslam.evaluation.rpe import rpe
    from flowslam.flow_eval import FlowEvaluation
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend

    cfg = with_weights(config, weights) if refined else network_only(config, weights)
    scored = set(sequence.holdout_pairs)
    scores = _SelfSupervisedScores(sequence.teacher, config.adapt.truncate_m, scored)
    gt_poses = sequence.dataset.gt_poses
    flow_sink = FlowEvaluation(np.asarray(gt_poses), scored) if gt_poses is not None else None

    def on_output(frame: Frame, out: FrontendOutput) -> None:
        scores.on_output(frame, out)
        if flow_sink is not None:
            flow_sink.on_output(frame, out)

    result = run_pipeline(sequence.dataset, make_frontend("ssf", cfg), make_backend("odometry", cfg),
                          sequence.scoring_frames(num_frames), on_output=on_output)
    if result.error is not None:
        raise result.error
    out = scores.result()
    if refined:
        out.update(_frontend_costs(result.frontend_stats, [result.indices.index(i) for i in sorted(scored)]))
    if gt_poses is not None:
        rows = [result.indices.index(i) for i in sequence.holdout_frames]
        out["rpe1_trans_m"] = rpe(result.poses[rows], np.asarray(gt_poses)[sequence.holdout_frames], delta=1)["rmse"]
        flow = flow_sink.result("ssf")["flow"]
        if flow:
            out["gt_flow"] = {k: flow[k] for k in ("EPE3D", "AccStrict", "EPE_3way", "EPE_FD", "DynamicIoU") if k in flow}
    return out


def compare_on_holdout(sequences, config: PipelineConfig, init_path: Path, adapted_path: Path,
                       num_frames: int) -> dict:
    """``{sequence path: {"start": scores, "adapted": scores}}`` (``score_weights``, network
    only), with ``adapt.report_refined`` also ``"start_refined"`` and ``"adapted_refined"``
    (the default ``ssf``)."""
    modes = (False, True) if config.adapt.report_refined else (False,)
    return {str(seq.path): {f"{name}{'_refined' if refined else ''}": score_weights(seq, config, path, num_frames,
                                                                                  refined)
                            for refined in modes for name, path in (("start", init_path), ("adapted", adapted_path))}
            for seq in sequences}
