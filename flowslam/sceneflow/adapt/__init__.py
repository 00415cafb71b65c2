"""Self-supervised adaptation of the scene-flow network to a user's own unlabelled logs
(``flowslam adapt``).

- ``teacher``: the refined ``ssf`` pipeline run once per sequence and cached (the
  distillation targets and the system's own poses);
- ``samples``: the network's input for a pair built as at inference, with the teacher's
  targets;
- ``loop``: the split (held-out tail), the loss, the epochs, early stopping, resume;
- ``report``: starting vs adapted weights on the held-out tails, in pipeline conditions.

The losses are in :mod:`flowslam.sceneflow.network.self_supervised`.
"""

from flowslam.sceneflow.adapt.loop import adapt, split_frames

__all__ = ["adapt", "split_frames"]
