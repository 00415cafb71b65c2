"""The learned scene-flow network (torch): model, layers, losses, samples, training, weights.

- :mod:`.voxelize` pillar encoding of T frames on a BEV grid;
- :mod:`.backbone` the spatio-temporal U-Net (STDCB blocks);
- :mod:`.flowssm`, :mod:`.selective_scan` the FlowSSM decoder and its chunked scan;
- :mod:`.model` ``SceneFlowNet`` (residual flow on the caller's ego prior + dynamic logit);
- :mod:`.losses` scene-adaptive / DeFlow losses, dynamic BCE;
- :mod:`.samples` network inputs from frames and ego priors (corrupted in training);
- :mod:`.train` the training loop (``torchrun -m flowslam.sceneflow.network.train``);
- :mod:`.weights` hash-checked weights files, the shipped ``ssf-tiny.pt``;
- :mod:`.propagate` the sampled output carried to every point of the scan.

Importing this package imports nothing heavy; the modules import torch.
"""
