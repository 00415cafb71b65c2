"""What a run writes besides the trajectories (``output:`` in the run config)."""

from __future__ import annotations

from pydantic import Field

from flowslam.config.base import StrictModel


class OutputConfig(StrictModel):
    """Optional outputs of a run folder."""

    static_map: bool = True
    """Write ``static_map.ply`` / ``.pcd`` and ``dynamic_points.ply`` (points marked dynamic removed, optimised poses)."""
    map_voxel_size: float = Field(0.2, gt=0)
    """Voxel size (m) of the static map."""
    map_points_per_frame: int = Field(10000, ge=1)
    """Points kept per scan for the map (memory: ~80 kB per scan)."""
    plot: bool = True
    """Write ``trajectory_topview.png`` (estimate vs GT from above, loops in red, object tracks)."""
    min_track_scans: int = Field(2, ge=1)
    """``moving_objects.csv`` and the top view's tracks list the objects of tracks seen in at
    least this many scans (1: every object of every scan). A track that one scan alone
    saw is mostly a false mover: on fresh simulated ``dt`` sequences 25-46 % of such rows
    were moving objects against 96-99 % of the rows of tracks of 3 or more scans (stop 58;
    ``rush-hour``: 50-60 %). What the frontend labels dynamic is not changed by this."""
