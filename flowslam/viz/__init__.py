"""3-D view of a run with rerun (the optional extra ``viz``: ``pip install flowslam[viz]``).

- :mod:`.recorder`: :class:`~.recorder.RerunRecorder` writes an ``.rrd`` file: scans
  coloured static/dynamic, flow arrows, trajectory and GT, loop closures, object boxes
  with velocity arrows and track ids, the static map; one timeline ``frame`` (scan index).
- :mod:`.live`: :class:`~.live.LiveRecorder`, a :class:`flowslam.Slam` step listener
  (``flowslam run --rerun FILE.rrd``).
- :mod:`.from_results`: :func:`~.from_results.record_results` builds a recording after
  the fact from a results folder (``flowslam view RESULTS_DIR``).

Nothing else in flowslam imports this package; rerun is imported only here, through
:func:`import_rerun`, which turns its absence into one ``InputError`` line.
"""

from __future__ import annotations

from flowslam.errors import InputError

INSTALL_HINT = "the 3-D view needs rerun-sdk, which is not installed: pip install flowslam[viz]"


def import_rerun():
    """The ``rerun`` module, or ``InputError`` (one line: how to install it)."""
    try:
        import rerun
    except ImportError:
        raise InputError(None, INSTALL_HINT) from None
    return rerun
