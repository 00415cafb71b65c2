"""``write_preview()``: a PNG top view of a simulated sequence, for a person to look at.

Left: the map (points of up to ``map_frames`` frames in the world frame, coloured by
class) with the ego path. Right: one frame in its sensor frame, static points by
class (faded), dynamic points coloured by the speed of their object (own motion,
``flow_compensated``) with arrows of that motion. Written from the files on disk (any
simulated sequence), palette-quantised to stay small.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowslam.simulation import labels


def write_preview(sequence_dir: str | Path, path: str | Path | None = None, frame: int | None = None,
                  map_frames: int = 24, dpi: int = 90) -> Path:
    """Write the preview of the simulation at ``sequence_dir`` (default ``<dir>/preview.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from flowslam.datasets.simulated import SimulatedSequence

    ds = SimulatedSequence(sequence_dir)
    n = len(ds)
    path = Path(path) if path is not None else ds.root / "preview.png"
    frame = n // 2 if frame is None else int(frame)
    if not 0 <= frame < n:
        from flowslam.errors import InputError

        raise InputError(path, f"frame {frame} is outside the sequence's {n} frames")
    rng = np.random.default_rng(0)
    colors = labels.CLASS_COLORS

    fig, (ax_map, ax_frame) = plt.subplots(1, 2, figsize=(14, 7.4), dpi=dpi)
    fig.patch.set_facecolor("white")
    # ---- map
    poses = ds.gt_poses
    pick = np.unique(np.linspace(0, n - 1, min(n, map_frames)).round().astype(int))
    per = max(4000, 240000 // max(len(pick), 1))
    pts, cls, dyn = [], [], []
    for i in pick:
        f = ds[i]
        p = ds.deskewed(i) if f.point_times is not None else f.points
        sel = rng.choice(len(p), size=min(per, len(p)), replace=False)
        pw = p[sel] @ poses[i][:3, :3].T + poses[i][:3, 3]
        pts.append(pw)
        cls.append(f.gt_class[sel])
        dyn.append(f.gt_dynamic[sel])
    pts, cls, dyn = np.concatenate(pts), np.concatenate(cls), np.concatenate(dyn)
    order = np.argsort(pts[:, 2])  # draw low points first, roofs on top
    ax_map.scatter(pts[order, 0], pts[order, 1], s=0.3, c=colors[cls[order]], linewidths=0, rasterized=True)
    ax_map.scatter(pts[dyn, 0], pts[dyn, 1], s=0.6, c="red", linewidths=0, rasterized=True)
    xy = poses[:, :2, 3]
    ax_map.plot(xy[:, 0], xy[:, 1], "-", color="black", lw=1.4)
    ax_map.plot(xy[0, 0], xy[0, 1], "o", color="black", ms=5)
    ax_map.plot(xy[frame, 0], xy[frame, 1], "s", color="white", mec="black", ms=6)
    ax_map.set_aspect("equal")
    ax_map.set_title("map: every %d-th frame by class, dynamic in red; ego path (o start, square = right)" %
                     max(1, int(np.round(n / max(len(pick), 1)))), fontsize=9)
    ax_map.set_xlabel("x (m), first frame's sensor frame", fontsize=8)
    ax_map.tick_params(labelsize=7)
    # ---- one frame
    f = ds[frame]
    p, c, d = f.points, f.gt_class, f.gt_dynamic
    own = f.extras["flow_compensated"]
    dt = float(ds.timestamps[min(frame + 1, n - 1)] - ds.timestamps[frame]) or 0.1
    st = ~d
    faded = 0.75 * colors[c[st]] + 0.25
    ax_frame.scatter(p[st, 0], p[st, 1], s=0.35, c=faded, linewidths=0, rasterized=True)
    speed = np.linalg.norm(own[d], axis=1) / dt
    sc = ax_frame.scatter(p[d, 0], p[d, 1], s=1.2, c=speed, cmap="plasma", vmin=0, vmax=max(2.0, np.percentile(
        speed, 98) if len(speed) else 2.0), linewidths=0, rasterized=True)
    if d.any():
        # one arrow per moving object: its mean own motion over 1 s
        inst = f.gt_instance[d]
        for k in np.unique(inst):
            m = inst == k
            c0 = p[d][m].mean(axis=0)
            v = own[d][m].mean(axis=0) / dt
            if np.linalg.norm(c0[:2]) < 48 and np.linalg.norm(v) > 0.3 and m.sum() >= 8:
                ax_frame.arrow(c0[0], c0[1], v[0], v[1], width=0.06, head_width=0.6, head_length=0.6,
                               color="black", length_includes_head=True, zorder=5)
        cb = fig.colorbar(sc, ax=ax_frame, fraction=0.035, pad=0.01)
        cb.set_label("speed of the object (m/s)", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    ax_frame.plot(0, 0, marker=(3, 0, -90), ms=10, color="black")
    ax_frame.set_xlim(-50, 50)
    ax_frame.set_ylim(-50, 50)
    ax_frame.set_aspect("equal")
    ax_frame.set_title(f"frame {frame}: {len(p)} points, {int(d.sum())} dynamic; arrows: object motion per second",
                       fontsize=9)
    ax_frame.set_xlabel("x (m), sensor frame", fontsize=8)
    ax_frame.tick_params(labelsize=7)
    present = [k for k in np.unique(np.concatenate([cls, c])) if k != labels.UNLABELED]
    handles = [Line2D([], [], marker="s", ls="", color=colors[k], label=labels.CLASS_NAMES[k]) for k in present]
    ax_map.legend(handles=handles, fontsize=7, loc="upper right", ncol=2, framealpha=0.85, markerscale=0.9)
    m = ds.manifest
    stats = m.get("stats", {})
    share = stats.get("dynamic_share", 0.0)
    fig.suptitle(
        f"flowslam simulate: preset {m.get('preset')}, seed {m.get('seed')}, sensor {m.get('sensor', {}).get('name')} "
        f"{m.get('sensor', {}).get('beams')}x{m.get('sensor', {}).get('columns')}, {n} frames, "
        f"{m.get('route', {}).get('length_m', 0):.0f} m, distortion {'on' if m.get('distortion') else 'off'}; "
        f"dynamic points/frame {stats.get('dynamic_points_per_frame', {}).get('mean', 0):.0f} ({100 * share:.1f} %)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.01, 1, 0.96))
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    _quantize(tmp, path)
    return path


def _quantize(src: Path, dst: Path, colors: int = 96) -> None:
    """Palette PNG (much smaller for scatter plots)."""
    try:
        from PIL import Image

        with Image.open(src) as im:
            im.convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT).save(dst, optimize=True)
        src.unlink()
    except ImportError:  # pragma: no cover - Pillow ships with matplotlib
        src.replace(dst)
