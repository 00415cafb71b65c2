"""Moving-object metrics on hand-computed cases (``flowslam.sceneflow.object_metrics``),
then through ``flowslam flow-eval``'s sink on a simulated sequence."""

import numpy as np
import pytest

from flowslam.sceneflow.object_metrics import ObjectScores, match_instances, miss_reasons


def _ids(*runs: tuple[int, int]) -> np.ndarray:
    """Per-point ids from (id, count) runs, in order."""
    return np.concatenate([np.full(n, i) for i, n in runs])


def test_match_instances_cover_and_iou_rules():
    # GT object 1: 100 points; predicted 7 holds 80 of them + 20 others -> cover 0.8, IoU 80/120
    # GT object 2: 100 points; predicted 8 holds 60 of them + 90 others -> cover 0.6, IoU 60/190 < 0.5
    # GT object 3: 30 points (< 50: not an object); predicted 9: 60 points of the background
    gt = _ids((1, 100), (2, 100), (3, 30), (-1, 20), (-1, 90), (-1, 60))
    pred = _ids((7, 80), (-1, 20), (8, 60), (-1, 40), (-1, 30), (7, 20), (8, 90), (9, 60))
    found, gt_objects, pred_objects = match_instances(pred, gt)
    assert found == {1: 7}
    assert gt_objects == [1, 2] and pred_objects == [7, 8, 9]
    # looser IoU: object 2 is found too
    found, _, _ = match_instances(pred, gt, min_iou=0.3)
    assert found == {1: 7, 2: 8}


def test_the_largest_overlap_is_the_candidate():
    # GT object 1 (100 points) split 55 / 45 between predicted 4 and 5: 4 is the candidate
    gt = _ids((1, 100))
    pred = _ids((4, 55), (5, 45))
    found, _, pred_objects = match_instances(pred, gt, min_points=40)
    assert found == {1: 4} and pred_objects == [4, 5]
    assert match_instances(pred, gt, min_cover=0.6)[0] == {}  # 55 % < 60 %


def test_an_instance_under_min_points_finds_a_small_object_but_is_no_predicted_object():
    # GT object 1: 56 points (a walker at range); predicted 3 holds 45 of them -> cover and
    # IoU 45/56: found, although 45 < 50 points makes 3 no predicted object
    # predicted 4: 30 background points, also under 50: neither found nor counted
    gt = _ids((1, 56), (-1, 30))
    pred = _ids((3, 45), (-1, 11), (4, 30))
    found, gt_objects, pred_objects = match_instances(pred, gt)
    assert found == {1: 3} and gt_objects == [1] and pred_objects == []
    scores = ObjectScores()
    scores.add(pred, gt, {}, {}, {})
    r = scores.result()
    assert r["recall"] == 1.0 and r["predicted_objects"] == 0 and r["precision"] is None
    # with a 60-point false object beside it, precision is 0 of 1 (the small finder is not counted)
    scores.add(np.concatenate([pred, np.full(60, 9)]), np.concatenate([gt, np.full(60, -1)]), {}, {}, {})
    r = scores.result()
    assert r["recall"] == 1.0 and r["predicted_objects"] == 1 and r["precision"] == 0.0


def test_object_scores_recall_precision_velocity_and_id_switches():
    scores = ObjectScores()
    gt = _ids((1, 100), (2, 100))
    pred = _ids((7, 100), (-1, 100))
    v_gt = {1: np.array([10.0, 0.0, 0.0]), 2: np.array([0.0, 5.0, 0.0])}
    # pair 1: object 1 found (track 0); object 2 missed; a false predicted object (9)
    scores.add(np.concatenate([pred, np.full(60, 9)]), np.concatenate([gt, np.full(60, -1)]),
               {7: np.array([9.0, 1.0, 0.0]), 9: np.zeros(3)}, v_gt, {7: 0, 9: 1})
    # pair 2: both found; object 1 now by track 3 (a switch)
    scores.add(_ids((7, 100), (8, 100)), gt, {7: np.array([10.0, 0.0, 0.0]), 8: np.array([0.0, 4.0, 0.0])},
               v_gt, {7: 3, 8: 2})
    # pair 3: object 1 by track 3 again (no switch)
    scores.add(pred, gt, {7: np.array([10.0, 0.0, 0.0])}, v_gt, {7: 3})
    r = scores.result()
    assert (r["gt_objects"], r["predicted_objects"], r["found"]) == (6, 5, 4)
    assert r["recall"] == pytest.approx(4 / 6)
    assert r["precision"] == pytest.approx(4 / 5)
    speed = [abs(np.hypot(9, 1) - 10), 0.0, 1.0, 0.0]
    velocity = [np.hypot(1, 1), 0.0, 1.0, 0.0]
    assert r["median_speed_error_mps"] == pytest.approx(np.median(speed))
    assert r["median_velocity_error_mps"] == pytest.approx(np.median(velocity))
    assert r["id_switches_per_100_pairs"] == pytest.approx(100 / 3)


def test_each_missed_object_gets_one_reason():
    # GT 1 (100 points): 40 called dynamic (instance 5) -> under half flagged: unflagged
    # GT 2 (100): 90 flagged, in pieces of 45 / 45 (instances 6, 7) -> no piece covers half: split
    # GT 3 (100): all in instance 8, which also holds 150 background points -> IoU 0.4: merged
    # GT 4 (100): all in instance 9 alone -> found, no reason
    gt = _ids((1, 100), (2, 100), (3, 100), (4, 100), (-1, 150))
    pred = _ids((5, 40), (-1, 60), (6, 45), (7, 45), (-1, 10), (8, 100), (9, 100), (8, 150))
    found, gt_objects, _ = match_instances(pred, gt)
    assert found == {4: 9}
    assert miss_reasons(pred, gt, found, gt_objects) == {1: "unflagged", 2: "split", 3: "merged"}
    scores = ObjectScores()
    scores.add(pred, gt, {}, {}, {})
    r = scores.result()
    assert (r["missed_unflagged"], r["missed_split"], r["missed_merged"]) == (1, 1, 1)
    assert r["gt_objects"] - r["found"] == 3  # the reasons account for every miss
    # none of its points flagged at all is unflagged too, even with no cover asked
    assert miss_reasons(np.full(100, -1), _ids((1, 100)), {}, [1], min_cover=0.0) == {1: "unflagged"}


def test_nothing_to_count_gives_none():
    r = ObjectScores().result()
    assert r["recall"] is None and r["precision"] is None and r["median_speed_error_mps"] is None


@pytest.mark.usefixtures("one_torch_thread")
def test_flow_eval_reports_object_metrics_for_ssf_on_simulation(tmp_path):
    from flowslam.config import PipelineConfig
    from flowslam.flow_eval import evaluate_flow
    from flowslam.simulation import simulate

    simulate(tmp_path / "dt", preset="dt", frames=6, seed=21, sensor="vlp32c")
    gt = evaluate_flow(tmp_path / "dt", PipelineConfig(frontend="gt", backend="odometry"))["objects"]
    assert gt["recall"] == 1.0 and gt["precision"] == 1.0 and gt["median_speed_error_mps"] < 1e-6
    ssf = evaluate_flow(tmp_path / "dt", PipelineConfig(frontend="ssf", backend="odometry"))["objects"]
    assert ssf["gt_objects"] == gt["gt_objects"] > 0
    assert 0 < ssf["found"] <= ssf["gt_objects"]
    assert ssf["missed_unflagged"] + ssf["missed_split"] + ssf["missed_merged"] == ssf["gt_objects"] - ssf["found"]
    assert ssf["median_speed_error_mps"] is not None and ssf["median_speed_error_mps"] < 1.0


def test_flow_eval_scores_objects_also_in_the_flow_metrics_region():
    """Two moving GT objects found exactly, one 10 m ahead and one 45 m ahead: the flow
    metrics' region (|x|, |y| <= 35 m, non-ground) holds only the first."""
    from flowslam.flow_eval import FlowEvaluation
    from flowslam.frame import Frame
    from flowslam.interfaces import FrontendOutput

    rng = np.random.default_rng(0)
    points = np.concatenate([rng.normal([10.0, 0.0, 0.5], 0.3, (60, 3)), rng.normal([45.0, 0.0, 0.5], 0.3, (60, 3))])
    ids = np.repeat([7, 8], 60)
    flow = np.tile([1.0, 0.0, 0.0], (120, 1))  # the sensor stands still, both objects drive 10 m/s
    frames = [Frame(i, 0.1 * i, points, gt_pose=np.eye(4), gt_flow=flow, gt_dynamic=np.ones(120, bool),
                    gt_instance=ids) for i in range(2)]
    sink = FlowEvaluation(np.stack([np.eye(4)] * 2))
    for frame in frames:
        sink.on_output(frame, FrontendOutput(frame.index, np.eye(4) if frame.index else None, flow=flow,
                                             static_mask=np.zeros(120, bool), instance_ids=ids))
    result = sink.result("exact")
    assert (result["objects"]["gt_objects"], result["objects"]["found"]) == (2, 2)
    assert (result["objects_in_region"]["gt_objects"], result["objects_in_region"]["found"]) == (1, 1)
