"""How precise is the network's own flow as its ego prior gets worse? (an evaluation, not a test)

For samples of a sequence with GT (default: the held-out simulated ``dt`` validation
sequence), the prior of the newest step is corrupted with ``PriorNoise`` scaled by each
``--scales`` value (1 = the training range: up to 1.5 m and 5 deg yaw; 0 = the exact GT
motion) and the network's flow alone (no test-time refinement) is compared with the GT
flow: mean EPE on static and on moving points, next to the error of the prior itself on
the static points (what the network has to remove).

    python tools/sceneflow_prior_sweep.py SEQUENCE [--weights FILE] [--scales 0 0.2 0.5 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--weights", type=Path, help="weights file (default: the shipped ones)")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.2, 0.5, 1.0])
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--points", type=int, default=8192)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from flowslam.datasets import open_dataset
    from flowslam.sceneflow.network.model import full_flow
    from flowslam.config import PriorNoise
    from flowslam.sceneflow.network.samples import training_sample
    from flowslam.sceneflow.network.weights import build_model, load_weights, shipped_weights

    path = args.weights or shipped_weights()
    model = build_model(load_weights(path, require_hash=args.weights is None)).eval()
    ds = open_dataset(args.sequence)
    T = model.config.num_frames
    newest = np.linspace(T - 1, len(ds) - 1, args.samples).astype(int)
    print(f"{path.name} on {args.sequence.name}: {len(newest)} samples, {args.points} points per frame")
    print("scale  static EPE (m)  moving EPE (m)  prior error, static (m)")
    for scale in args.scales:
        noise = PriorNoise(max_translation_m=1.5 * scale, max_yaw_deg=5 * scale, max_z_m=0.1 * scale,
                           max_roll_pitch_deg=0.5 * scale, p_no_prior=0.0)
        rng = np.random.default_rng(0)
        static_err, moving_err, prior_err = [], [], []
        for k in newest:
            s = training_sample(ds, int(k), T, noise, rng, args.points)
            with torch.no_grad():
                out = model({"points": [[torch.from_numpy(p) for p in s.points]]})
            pred = full_flow(s.source_points, s.points[-2], out["flow"].numpy())
            err = np.linalg.norm(pred - s.gt_flow, axis=1)
            static_err.append(err[~s.dynamic].mean())
            if s.dynamic.any():
                moving_err.append(err[s.dynamic].mean())
            prior_err.append(np.linalg.norm(s.residual[~s.dynamic], axis=1).mean())
        moving = f"{np.mean(moving_err):14.3f}" if moving_err else f"{'-':>14}"
        print(f"{scale:5.2f}  {np.mean(static_err):14.3f}  {moving}  {np.mean(prior_err):23.3f}")


if __name__ == "__main__":
    main()
