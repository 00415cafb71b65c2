#!/usr/bin/env bash
# Reproduce the shipped scene-flow weights (flowslam/sceneflow/weights/ssf-tiny.pt) on a CPU:
# simulate the training and held-out validation sequences, train for a wall-clock budget,
# export the best checkpoint with its SHA-256. Usage: tools/reproduce_weights.sh [WORK_DIR] [MINUTES]
set -euo pipefail
WORK=${1:-runs/reproduce-weights}
MINUTES=${2:-45}
mkdir -p "$WORK"
sim() { flowslam simulate --no-progress --overwrite --frames "$4" --preset "$1" --seed "$2" --sensor "$3" "$WORK/$5"; }
sim dt 1 hdl64 48 train_dt_1_hdl64
sim dt 2 hdl64 48 train_dt_2_hdl64
sim dh 3 hdl64 48 train_dh_3_hdl64
sim rush-hour 4 hdl64 48 train_rush-hour_4_hdl64
sim static 5 hdl64 48 train_static_5_hdl64
sim dt 6 vlp32c 48 train_dt_6_vlp32c
sim rush-hour 7 os1-128 48 train_rush-hour_7_os1-128
sim dt 8 vlp16 48 train_dt_8_vlp16
sim dt 99 hdl64 24 val_dt_99_hdl64          # held out: a seed never trained on
flowslam train "$WORK"/train_* --val "$WORK/val_dt_99_hdl64" --out-dir "$WORK/out" \
    --preset tiny --frames 5 --max-points 8192 --epochs 3 --batch-size 2 --lr 0.003 \
    --max-minutes "$MINUTES" --seed 0 --export "$WORK/ssf-tiny.pt"
