"""Scene-flow weights files: export, hash check, safe loading.

A weights file is ``torch.save({"format": "flowslam-sceneflow", "version": 1,
"model_config": {...}, "state_dict": {...}, "meta": {...}})``: plain tensors and
JSON-like values only, so it loads with ``torch.load(weights_only=True)`` (no pickle
code runs). Beside it, ``<file>.sha256`` records its SHA-256; loading refuses a file
whose hash differs (a tampered or truncated file). The shipped weights live in
``flowslam/sceneflow/network/weights/`` inside the package.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch

from flowslam.errors import InputError

FORMAT = "flowslam-sceneflow"
SHIPPED_DIR = Path(__file__).with_name("weights")
SHIPPED_NAME = "ssf-tiny.pt"


def shipped_weights() -> Path:
    """Path of the weights shipped inside the package (used by ``--frontend ssf``)."""
    return SHIPPED_DIR / SHIPPED_NAME


def sha256_of(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _sidecar(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


def save_weights(path: str | Path, model_config: dict, state_dict: dict, meta: dict | None = None) -> str:
    """Write a weights file and its ``.sha256`` sidecar; returns the hash."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "version": 1,
        "model_config": model_config,
        "state_dict": {k: v.detach().cpu().contiguous() for k, v in state_dict.items()},
        "meta": meta or {},
    }
    torch.save(payload, path)
    digest = sha256_of(path)
    _sidecar(path).write_text(f"{digest}  {path.name}\n")
    return digest


def load_weights(path: str | Path, *, require_hash: bool = True) -> dict:
    """Verify the hash (sidecar ``.sha256``) and load with ``weights_only=True``. The
    file's SHA-256 is returned in ``payload["sha256"]``.

    Raises ``InputError`` for a missing file, a missing sidecar (when
    ``require_hash``), a hash mismatch, or a file that is not flowslam weights.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "weights file does not exist")
    if path.stat().st_size == 0:
        raise InputError(path, "weights file is empty")
    sidecar = _sidecar(path)
    actual = sha256_of(path)
    if sidecar.is_file():
        expected = sidecar.read_text().split()[0] if sidecar.read_text().split() else ""
        if actual != expected:
            raise InputError(path, f"SHA-256 {actual[:12]}... differs from the recorded {expected[:12]}... "
                                   f"({sidecar.name}): refusing a modified or damaged weights file")
    elif require_hash:
        raise InputError(path, f"no recorded hash ({sidecar.name}) beside the weights file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is bad input
        first_line = (str(e).splitlines() or ["no message"])[0]
        raise InputError(path, f"cannot load weights ({e.__class__.__name__}: {first_line})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(path, f"not a {FORMAT} weights file")
    payload["sha256"] = actual
    return payload


def build_model(payload: dict):
    """A ``SceneFlowNet`` in eval mode with the payload's config and weights."""
    from flowslam.sceneflow.network.model import ModelConfig, SceneFlowNet

    model = SceneFlowNet(ModelConfig(**payload["model_config"]))
    model.load_state_dict(payload["state_dict"])
    return model.eval()
