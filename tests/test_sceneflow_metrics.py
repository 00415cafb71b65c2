"""Scene-flow metrics: known answers on the real Argoverse 2 pair and on synthetic cases."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flowslam import geometry
from flowslam.sceneflow import metrics as M


@pytest.fixture(scope="module")
def av2_pair(av2_log: Path):
    from flowslam.datasets import open_dataset

    ds = open_dataset(av2_log)
    frame = ds[0]
    T_1_0 = geometry.relative(ds.gt_poses[1], ds.gt_poses[0])
    ego = geometry.transform_points(T_1_0, frame.points) - frame.points
    return frame, ego


def test_av2_perfect_odometry_objects_static_scores_0227(av2_pair):
    """Ego-motion flow for every point (perfect odometry, every object assumed static)."""
    f, ego = av2_pair
    out = M.three_way_epe(ego, f.gt_flow, f.gt_dynamic, f.gt_class, f.extras["is_ground"], f.points)
    assert out["EPE_3way"] == pytest.approx(0.227, abs=0.0005)
    assert out["EPE_FD"] == pytest.approx(0.674, abs=0.001)  # the movers' own motion
    assert out["EPE_BS"] < 0.001 and out["EPE_FS"] < 0.01  # labels' float16 rounding, sub-threshold boxes
    assert (out["count_FD"], out["count_FS"], out["count_BS"]) == (1819, 6450, 66027)
    # the AV2 dynamic rule (0.5 m/s = 0.05 m per 0.1 s sweep) reproduces the labels exactly
    assert np.array_equal(M.dynamic_from_flow(f.gt_flow, ego, dt=0.1), f.gt_dynamic)
    full = M.flow_metrics(ego, f.gt_flow, f.gt_dynamic, f.gt_class, f.extras["is_ground"], f.points, ego_flow=ego)
    assert full["EPE_3way"] == out["EPE_3way"]
    assert full["DynamicIoU"] == 0.0  # predicts nothing dynamic
    m = M.av2_eval_mask(f.points, f.extras["is_ground"])  # SSA: all static -> the static share
    assert full["SSA"] == pytest.approx(1.0 - f.gt_dynamic[m].mean())
    assert full["bucketed/Mean/dynamic"] == pytest.approx(1.0)  # zero residual: EPE == speed in every bucket


def test_av2_gt_flow_scores_zero(av2_pair):
    f, ego = av2_pair
    out = M.flow_metrics(f.gt_flow, f.gt_flow, f.gt_dynamic, f.gt_class, f.extras["is_ground"], f.points,
                         ego_flow=ego)
    for key in ("EPE3D", "EPE_FD", "EPE_FS", "EPE_BS", "EPE_3way", "Outliers", "bucketed/Mean/static",
                "bucketed/Mean/dynamic"):
        assert out[key] == 0.0, key
    assert out["AccStrict"] == out["AccRelax"] == out["DynamicIoU"] == out["SSA"] == 1.0


def test_segmentation_accuracy_known_answer():
    pred = np.array([True, True, False, False, False])
    gt = np.array([True, False, False, True, False])
    assert M.segmentation_accuracy(pred, gt) == pytest.approx(3 / 5)
    assert M.segmentation_accuracy(pred, gt, mask=np.array([1, 1, 0, 0, 0], bool)) == pytest.approx(1 / 2)
    assert math.isnan(M.segmentation_accuracy(pred[:0], gt[:0]))


def test_accuracy_and_outliers_known_answers():
    gt = np.array([[1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0], [10.0, 0, 0], [0.2, 0, 0]])
    err = np.array([0.04, 0.08, 0.2, 0.6, 0.05])  # relative: 4 %, 8 %, inf, 6 %, 25 %
    pred = gt + np.array([[0, e, 0] for e in err])
    assert M.epe3d(pred, gt) == pytest.approx(err.mean())
    # strict: EPE < 0.05 or rel < 5 %: rows 0 only (row 4 has EPE exactly 0.05, not below)
    assert M.acc_strict(pred, gt) == pytest.approx(1 / 5)
    # relax: EPE < 0.1 or rel < 10 %: rows 0, 1, 3, 4
    assert M.acc_relax(pred, gt) == pytest.approx(4 / 5)
    # outliers: EPE > 0.3 or rel > 10 %: row 2 (rel inf), row 3 (EPE .6), row 4 (rel 25 %)
    assert M.outliers(pred, gt) == pytest.approx(3 / 5)
    assert math.isnan(M.epe3d(pred[:0], gt[:0]))


def test_three_way_masks_ground_box_and_parts():
    pts = np.array([[1.0, 1, 0], [2, 2, 0], [3, 3, 0], [4, 4, 0], [40, 0, 0], [5, 5, 0]])
    gt = np.zeros((6, 3))
    pred = np.zeros((6, 3))
    pred[:, 0] = [0.3, 0.1, 0.02, 9.0, 9.0, 9.0]
    classes = np.array([19, 19, 0, 0, 0, 17])
    dynamic = np.array([True, False, False, False, False, False])
    ground = np.array([False, False, False, False, False, True])
    out = M.three_way_epe(pred, gt, dynamic, classes, ground, pts)
    # row 3 background static but EPE 9 counts; row 4 is outside the box, row 5 is ground
    assert out["EPE_FD"] == pytest.approx(0.3)
    assert out["EPE_FS"] == pytest.approx(0.1)
    assert out["EPE_BS"] == pytest.approx((0.02 + 9.0) / 2)
    assert out["EPE_3way"] == pytest.approx((0.3 + 0.1 + 4.51) / 3)
    # no dynamic points: FD is NaN and left out of the average
    out = M.three_way_epe(pred, gt, np.zeros(6, bool), classes, ground, pts)
    assert math.isnan(out["EPE_FD"]) and out["EPE_3way"] == pytest.approx((0.2 + 4.51) / 2)


def test_bucketed_epe_known_answers():
    car, ped, bg = 19, 17, 0
    # residual GT: car points at 1 m/s (0.1 m per 0.1 s) and 5 m/s; a static car point; pedestrians at 1.5 m/s
    gt = np.array([[0.1, 0, 0], [0.1, 0, 0], [0.5, 0, 0], [0.0, 0, 0], [0.15, 0, 0], [0.0, 0, 0]])
    pred = gt.copy()
    pred[0, 1] = 0.02  # EPE 0.02 in the 1.0-1.2 m/s bucket (with row 1: mean 0.01)
    pred[2, 1] = 0.25  # EPE 0.25 at 0.5 m per frame: normalised 0.5
    pred[3, 1] = 0.03  # static car point
    pred[4, 1] = 0.15  # pedestrian: normalised 1.0
    pred[5, 1] = 0.01  # background
    classes = np.array([car, car, car, car, ped, bg])
    out = M.bucketed_epe(pred, gt, classes, dt=0.1)
    assert out["CAR"]["static"] == pytest.approx(0.03)
    assert out["CAR"]["dynamic"] == pytest.approx(np.mean([0.01 / 0.1, 0.25 / 0.5]))
    assert out["PEDESTRIAN"]["dynamic"] == pytest.approx(1.0)
    assert math.isnan(out["PEDESTRIAN"]["static"])
    assert out["BACKGROUND"]["static"] == pytest.approx(0.01)
    assert math.isnan(out["OTHER_VEHICLES"]["static"])
    assert out["Mean"]["static"] == pytest.approx((0.01 + 0.03) / 2)
    assert out["Mean"]["dynamic"] == pytest.approx((0.3 + 1.0) / 2)


def test_dynamic_iou_and_categories():
    p = np.array([1, 1, 0, 0, 1], bool)
    g = np.array([1, 0, 1, 0, 1], bool)
    assert M.dynamic_iou(p, g) == pytest.approx(2 / 4)
    assert math.isnan(M.dynamic_iou(np.zeros(3, bool), np.zeros(3, bool)))
    assert M.AV2_CATEGORIES[19] == "REGULAR_VEHICLE" and M.AV2_CATEGORIES[17] == "PEDESTRIAN"
    assert len(M.AV2_CATEGORIES) == 31
