#!/usr/bin/env bash
# Device check on a CUDA machine (issues 12 and 14; not part of CI): the CUDA tests, the network
# stage per torch device (tools/bench_network_device.py) and the GPU training throughput of the
# tiny and full presets. For a machine that has torch with CUDA but none of open3d, gtsam,
# kiss-icp, rosbags (those paths are not exercised here): flowslam is installed without its
# dependencies into /tmp/fs, and pydantic & co. from wheels in WHEELS if that folder exists.
#   STEPS="tests bench train gain" (the default: all four)
#   FLOWSLAM_DATA=DIR (holding kitti-odometry-00-first16, frames 0-5 suffice)
#   TRAIN_DATA=DIR (simulated training sequences, e.g. written by tools/compact_sim.py; VAL names
#     the held-out one)   TRAIN_MIN=2 (per preset)   EPOCHS="tiny:20 full:20"
#   TRAIN_CONFIG='{"num_workers": 8, "val_samples": 12}' (flowslam train --config JSON)
#   EPOCHS entries are NAME:EPOCHS; NAME's part before the first "-" is the preset, and with
#     RUN_CONFIGS=DIR a NAME that has DIR/NAME.json trains with that config instead of TRAIN_CONFIG
#     (e.g. "tiny-fine:15" with DIR/tiny-fine.json holding init_weights and model_overrides)
#   BATCH=4  LR=0.003 (flowslam train --batch-size / --lr)
#   BENCH_ARGS="--grid-half-extent 38.4" (more options of tools/bench_network_device.py)
#   GAIN_SEQ=DIR (a simulated sequence for tools/bench_adapt.py gain: shipped weights against the
#     ones trained here, on GAIN_DEVICE=cuda)
#   OUT=DIR (logs, bench JSON, histories, weights)
#   tools/gpu_check.sh
R=$(pwd); PY=${PY:-python3}; TRAIN_MIN=${TRAIN_MIN:-2}; WHEELS=${WHEELS:-.whl}
STEPS=${STEPS:-tests bench train gain}; EPOCHS=${EPOCHS:-tiny:20 full:20}; BATCH=${BATCH:-4}; LR=${LR:-0.003}
TRAIN_CONFIG=${TRAIN_CONFIG:-'{"num_workers": 8, "val_samples": 12}'}
step() { [[ " $STEPS " == *" $1 "* ]]; }
export PYTHONUNBUFFERED=1
mkdir -p "${OUT:=/tmp/gpu-check}"
{
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
if [ -d "$WHEELS" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl || exit 1
fi
$PY -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --target /tmp/fs . >/dev/null 2>&1 || exit 1
export PYTHONPATH=/tmp/fs:/tmp/site
cd /tmp  # not the checkout: its flowslam/ folder lacks the plug-in packages
step tests && { echo "=== tests"; date; timeout 300 $PY -m pytest -q -p no:cacheprovider -rs "$R"/tests/test_sceneflow_model.py \
  "$R"/tests/test_network_speed_paths.py "$R"/tests/test_sceneflow_scan.py 2>&1 | tail -15; }
step bench && { echo "=== network stage per device"; date
timeout 300 $PY "$R"/tools/bench_network_device.py --frames 6 --runs 5 ${BENCH_ARGS:-} --json "$OUT"/bench_network_device.json; }
if step train && [ -n "${TRAIN_DATA:-}" ]; then
  echo "=== training"; date
  echo "$TRAIN_CONFIG" > /tmp/gpu-check-train.json
  mapfile -t seqs < <(find "$TRAIN_DATA" -mindepth 1 -maxdepth 1 -type d ! -path "$VAL")
  for pe in $EPOCHS; do
    name=${pe%%:*}; preset=${name%%-*}; config=/tmp/gpu-check-train.json
    [ -n "${RUN_CONFIGS:-}" ] && [ -f "$RUN_CONFIGS/$name.json" ] && config=$RUN_CONFIGS/$name.json
    timeout $(awk "BEGIN {print int($TRAIN_MIN * 60 + 90)}") $PY -m flowslam train "${seqs[@]}" --val "$VAL" \
      --out-dir /tmp/tr_$name --config "$config" --preset $preset --frames 5 --max-points 8192 \
      --epochs "${pe##*:}" --batch-size "$BATCH" --lr "$LR" --max-minutes "$TRAIN_MIN" --seed 0 --export "$OUT"/$name.pt \
      --no-progress > /tmp/train_$name.log 2>&1
    echo "--- $name"; tail -8 /tmp/train_$name.log; pkill -f "flowslam train" || true  # loader workers a timeout left
    cp /tmp/tr_$name/history.json "$OUT"/history_$name.json || echo "no history for $name"
  done
fi
if step gain && [ -n "${GAIN_SEQ:-}" ]; then
  echo "=== prior-error gain (tools/bench_adapt.py gain)"; date
  also=(); for w in "$OUT"/*.pt; do [ -f "$w" ] && also+=(--also "$w"); done
  timeout 150 $PY "$R"/tools/bench_adapt.py gain --sequence "$GAIN_SEQ" --device "${GAIN_DEVICE:-cuda}" --points 8192 \
    --out /tmp/gain "${also[@]}" && cp /tmp/gain/gain.json "$OUT"/gain.json
fi
date
} 2>&1 | tee "$OUT"/log.txt
