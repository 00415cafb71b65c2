"""Scene flow, in two wings:

- :mod:`flowslam.sceneflow.network` (torch): the learned flow network after MambaFlow
  (pillar encoding, spatio-temporal U-Net, FlowSSM decoder), its losses, training
  samples, training loop, hash-checked weights and the propagation of its sampled
  output to every point of a scan;
- :mod:`flowslam.sceneflow.refinement` (numpy / SciPy / Open3D): the test-time geometry
  that turns the network's output into odometry-grade flow and a segmentation: static
  refinement against the next scan, geometric movers (visibility), per-object rigid
  registration, mover tracking from pair to pair;

plus :mod:`flowslam.sceneflow.metrics` (numpy): EPE3D, accuracies, the Argoverse 2
3-way EPE and Dynamic IoU. Nothing here imports a frontend; the ``ssf`` frontend
(``flowslam.frontends.ssf``) chains these parts as stages.
"""
