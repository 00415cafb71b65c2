"""The ``ssf`` ablations of SSF-PAN Table I (``sf``, ``gt-seg``, ``gt-flow+ssf-seg``) through the
pipeline on a small simulated dt sequence with exact GT, and their refusal of data without GT."""

from __future__ import annotations


import numpy as np
import pytest

from cli_helpers import assert_one_line_error, flowslam
from flowslam import geometry
from flowslam.datasets import open_dataset


@pytest.fixture(scope="module")
def sim_dt(tmp_path_factory):
    from flowslam.simulation import simulate

    out = tmp_path_factory.mktemp("sim") / "dt"
    simulate(out, preset="dt", frames=6, seed=21, sensor="vlp32c")
    return out


def _run(name, sim, frames=None):
    """(RunResult, [(frame, FrontendOutput)]) of frontend ``name`` with the odometry backend."""
    from flowslam.config import load_config
    from flowslam.pipeline import run_pipeline
    from flowslam.registry import make_backend, make_frontend

    config = load_config(frontend=name)
    outputs = []
    result = run_pipeline(open_dataset(sim), make_frontend(name, config), make_backend("odometry", config),
                          frames=frames, on_output=lambda frame, out: outputs.append((frame, out)))
    assert result.error is None, result.error
    return result, outputs


def _pairs(outputs):
    """(scan k-1, output of scan k) for every scan with a predecessor."""
    return [(outputs[k - 1][0], out) for k, (_, out) in enumerate(outputs) if k > 0]


def _translation_errors(result, sim):
    gt = open_dataset(sim).gt_poses
    return [geometry.translation_norm(geometry.inv(geometry.inv(gt[k]) @ gt[k + 1]) @ T)
            for k, T in enumerate(result.odometry)]


def test_sf_registers_every_point_with_the_network_flow_and_segments_nothing(sim_dt, one_torch_thread):
    result, outputs = _run("sf", sim_dt)
    assert len(result.odometry) == 5
    for prev, out in _pairs(outputs):
        assert out.static_mask is None and out.instance_ids is None
        assert out.flow.shape == prev.points.shape and not np.allclose(out.flow, prev.gt_flow)
        assert out.stats["n_static"] == out.stats["n_points"] == len(prev.points)  # all finite pairs
        assert not out.stats["fallback"]
        assert set(out.stats["stage_ms"]) == {"network", "no_segmentation", "flow_to_pose"}  # no refinement


def test_gt_seg_uses_the_gt_labels_with_the_refined_predicted_flow(sim_dt, one_torch_thread):
    result, outputs = _run("gt-seg", sim_dt)
    for prev, out in _pairs(outputs):
        np.testing.assert_array_equal(out.static_mask, ~prev.gt_dynamic)
        np.testing.assert_array_equal(out.instance_ids, np.where(prev.gt_dynamic, prev.gt_instance, -1))
        assert not np.allclose(out.flow, prev.gt_flow, atol=1e-3)  # the flow is predicted, never GT
        assert out.stats["refine_accepted"] and "objects" not in out.stats["stage_ms"]
    assert max(_translation_errors(result, sim_dt)) < 0.02


def test_gt_flow_with_ssf_segmentation_registers_gt_flow_of_the_predicted_static_points(sim_dt, one_torch_thread):
    result, outputs = _run("gt-flow+ssf-seg", sim_dt)
    assert max(_translation_errors(result, sim_dt)) < 0.002  # exact GT flow: mm-level
    for prev, out in _pairs(outputs):
        np.testing.assert_array_equal(out.flow, prev.gt_flow)
        assert (out.static_mask != ~prev.gt_dynamic).any()  # predicted: not the GT labels
        assert out.stats["n_static"] == int(out.static_mask.sum())  # registered: the predicted static points
        assert (out.instance_ids >= 0).any()  # the objects stage's instances
    # on the first pair the chain sees the same input as ssf's: the same segmentation
    _, ssf = _run("ssf", sim_dt, frames=range(2))
    np.testing.assert_array_equal(outputs[1][1].static_mask, ssf[1][1].static_mask)
    np.testing.assert_array_equal(outputs[1][1].instance_ids, ssf[1][1].instance_ids)


@pytest.mark.parametrize("name, missing", [("gt-seg", "no ground-truth dynamic labels"),
                                           ("gt-flow+ssf-seg", "no ground-truth flow")])
def test_gt_ablations_refuse_kitti_in_one_line(kitti_extract, tmp_path, name, missing):
    proc = flowslam("run", "-f", name, "--no-progress", "-n", "3", "-o", tmp_path, kitti_extract)
    assert_one_line_error(proc, "000000.bin", missing, name)
