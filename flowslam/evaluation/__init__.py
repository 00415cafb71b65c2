"""Trajectory evaluation: APE, RPE, KITTI drift, SSF-PAN Table I statistics."""
