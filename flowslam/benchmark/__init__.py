"""``flowslam bench``: frontends x variants x sequences, SSF-PAN's Table I and Fig. 7.

- :mod:`.suite` the default sequences (simulated at fixed seeds) and frontends, the
  kind of each frontend (SSF-PAN's marker convention);
- :mod:`.worker` one cell: a frontend run once over one sequence with ``a-loam``, its
  measurements replayed into ``s-loam``, in its own process (peak RSS per cell);
- :mod:`.runner` the loop over cells, resumable (a finished cell leaves ``cell.json``);
- :mod:`.report` ``table1.md`` / ``table1.csv`` / ``bench.json`` from the cells;
- :mod:`.plots` ``runtime_vs_rpe.png`` and ``trajectories_<sequence>.png``.
"""
