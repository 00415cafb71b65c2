"""What ``flowslam bench`` runs by default, and what kind of method each frontend is.

Default sequences (no data needed; simulated once into the cache of ``flowslam demo``,
64 x 1024 HDL-64E at 10 Hz, no motion distortion):

- ``dh``: SSF-PAN's D^H-like few-movers set (~100 dynamic points per frame);
- ``dt``: the D^T-like traffic set (~4,000 dynamic points per frame, a lead car);
- ``loop``: the demo's block loop, which comes back to its start (s-loam can close it).

Kinds follow SSF-PAN's Table I markers: ``●`` the method's own segmentation and flow;
``○`` ground-truth flow with the method's segmentation; ``◐`` the method's flow with
ground-truth segmentation; plus the baselines, the learned flow without segmentation
and the full ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from flowslam.config import VARIANTS as LOOP_CLOSURE_BY_VARIANT

SUITE_FRAMES = 300
"""Frames of the simulated ``dh`` and ``dt`` sequences."""

DEFAULT_SUITE: dict[str, dict] = {
    "dh": dict(preset="dh", seed=311, frames=SUITE_FRAMES, sensor="hdl64", columns=1024, distortion=False),
    "dt": dict(preset="dt", seed=312, frames=SUITE_FRAMES, sensor="hdl64", columns=1024, distortion=False),
    "loop": None,  # the demo sequence (flowslam.simulation.demo.DEMO_SETTINGS)
}
"""Name -> arguments of ``simulate()`` (None: the demo sequence)."""

DEFAULT_FRONTENDS = ("kiss-icp", "ransac", "sf", "ssf", "gt-seg", "gt-flow+ssf-seg", "gt-flow", "gt")
VARIANTS = tuple(LOOP_CLOSURE_BY_VARIANT)
"""The bench's variants, in table order: ``a-loam`` (loop closure off), ``s-loam`` (on)."""


@dataclass(frozen=True)
class Kind:
    marker: str
    """Table I marker (text)."""
    label: str
    """What the frontend is fed with."""
    plot_marker: str
    """matplotlib marker of Fig. 7 (one per kind)."""
    filled: bool


KINDS: dict[str, Kind] = {
    "ssf": Kind("●", "predicted segmentation and flow", "o", True),
    "sf": Kind("", "predicted flow, no segmentation", "D", True),
    "gt-flow+ssf-seg": Kind("○", "GT flow, predicted segmentation", "o", False),
    "gt-seg": Kind("◐", "predicted flow, GT segmentation", "s", False),
    "gt": Kind("GT", "GT flow and GT segmentation", "*", True),
    "gt-flow": Kind("GT", "GT flow, no segmentation", "P", True),
    "ransac": Kind("", "baseline: FPFH + RANSAC", "^", True),
    "kiss-icp": Kind("", "baseline: KISS-ICP", "v", True),
}
OTHER = Kind("", "other", "X", True)


def kind_of(frontend: str) -> Kind:
    return KINDS.get(frontend, OTHER)


def default_sequences(cache_dir: str | Path | None = None, frames: int | None = None) -> dict[str, Path]:
    """The default suite's sequences, simulated into the cache when missing; ``frames``
    shortens every one (a quick look; the cache key changes with it)."""
    from flowslam.simulation.demo import DEMO_SETTINGS, ensure_sequence

    out = {}
    for name, settings in DEFAULT_SUITE.items():
        settings = dict(DEMO_SETTINGS if settings is None else settings)
        if frames is not None:
            settings["frames"] = frames
        out[name] = ensure_sequence("demo" if name == "loop" and frames is None else f"bench-{name}", settings,
                                    cache_dir)
    return out
