"""Which torch device runs the network: the one place that names CUDA (the model code
itself stays device-agnostic, ``tests/test_sceneflow_model.py``)."""

from __future__ import annotations

import torch

__all__ = ["inference_device"]


def inference_device(choice: str) -> torch.device:
    """The ``torch.device`` of ``choice``: ``"auto"`` is the first CUDA device when torch
    sees one, else the CPU; any other string is taken as it is (``"cpu"``, ``"cuda:1"``)."""
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)
