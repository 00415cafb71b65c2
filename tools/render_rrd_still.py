"""A still image of one frame of a flowslam .rrd recording, drawn with matplotlib (top view).

Not a screenshot of the rerun viewer (no headless way to render it here): the same
recorded data, read back with rerun's own reader (``rerun.chunk.RrdReader``) and
plotted: the scan coloured static/dynamic, flow arrows, object boxes with velocity
arrows and track ids, the estimated path and GT; world frame, metres.

    .venv/bin/python tools/render_rrd_still.py run.rrd --frame 3 --out docs/images/view_still.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def latest_at(path: Path, frame: int) -> dict[str, dict[str, object]]:
    """Entity -> {component column: value of the last row at or before ``frame``}."""
    from rerun.chunk import RrdReader

    best: dict[str, tuple[int, dict]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if "frame" not in chunk.timeline_names:
            continue
        batch = chunk.to_record_batch()
        frames = batch.column("frame").to_pylist()
        for row, f in enumerate(frames):
            if f is not None and f <= frame and f >= best.get(chunk.entity_path, (-1, {}))[0]:
                best[chunk.entity_path] = (f, {name: batch.column(name)[row].as_py() for name in batch.schema.names
                                               if ":" in name})
    return {entity: values for entity, (_, values) in best.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", type=Path)
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    data = latest_at(args.rrd, args.frame)
    fig, ax = plt.subplots(figsize=(9, 7), dpi=110)
    scan = data.get("/world/scan", {})
    pts = np.array(scan.get("Points3D:positions") or np.zeros((0, 3)))
    cls = np.array(scan.get("Points3D:class_ids") or np.zeros(len(pts)))
    for c, colour, label in ((1, "#5087d7", "static"), (0, "#aaaaaa", "unlabelled"), (2, "#f03232", "dynamic")):
        own = pts[cls == c]
        if len(own):
            ax.scatter(own[:, 0], own[:, 1], s=0.3 if c != 2 else 1.5, c=colour, label=f"scan: {label}", lw=0)
    flow = data.get("/world/flow", {})
    if flow:
        o, v = np.array(flow["Arrows3D:origins"]), np.array(flow["Arrows3D:vectors"])
        moving = np.linalg.norm(v, axis=1) > 0.05
        ax.quiver(o[moving, 0], o[moving, 1], v[moving, 0], v[moving, 1], angles="xy", scale_units="xy", scale=0.25,
                  color="#fa9a1e", width=0.002, label="flow (ego-compensated, x4)")
    boxes = data.get("/world/objects", {})
    for c, h, label in zip(boxes.get("Boxes3D:centers") or [], boxes.get("Boxes3D:half_sizes") or [],
                           boxes.get("Boxes3D:labels") or []):
        ax.add_patch(Rectangle((c[0] - h[0], c[1] - h[1]), 2 * h[0], 2 * h[1], fill=False, color="k", lw=0.8))
        ax.annotate(label, (c[0] + h[0], c[1] + h[1]), fontsize=6)
    vel = data.get("/world/objects/velocity", {})
    if vel:
        o, v = np.array(vel["Arrows3D:origins"]), np.array(vel["Arrows3D:vectors"])
        ax.quiver(o[:, 0], o[:, 1], v[:, 0], v[:, 1], angles="xy", scale_units="xy", scale=1, color="#e6b800",
                  width=0.004, label="object velocity (1 s)")
    for entity, style, label in (("/world/trajectory/gt", "--", "GT"), ("/world/trajectory/estimate", "-", "estimate")):
        strips = data.get(entity, {}).get("LineStrips3D:strips")
        if strips:
            s = np.array(strips[0])
            ax.plot(s[:, 0], s[:, 1], style, lw=2, label=label)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world = first scan)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{args.rrd.name}, frame {args.frame} (matplotlib top view of the recorded data)")
    ax.legend(loc="upper right", fontsize=7, markerscale=8)
    half = 45
    centre = np.array(data.get("/world/sensor", {}).get("Transform3D:translation") or [[0, 0, 0]])[0]
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half * 0.75, centre[1] + half * 0.75)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
