"""Test-time geometry of ``ssf`` (numpy / SciPy / Open3D, no torch).

Frames: ``source`` = scan k-1 in its sensor frame, ``target`` = scan k in its sensor
frame, ``T_ego`` / ``T_curr_prev`` = ``T_{k,k-1}``; flow in the Argoverse 2 convention.

- :mod:`.static` flow-guided point-to-plane ICP of the static points, snapped pairs;
- :mod:`.visibility` geometric movers (off scan k's surface, seen through in its range image);
- :mod:`.clusters` BEV connected components and a local ground test;
- :mod:`.objects` per-object rigid registration, per-point choice of motion, instances;
- :mod:`.tracking` ``MoverPrior``: the movers of one pair carried to the next.
"""
