"""Frontends and backends by name, so ``--frontend NAME --backend NAME`` can pick them.

Built-ins are registered as ``"module:attribute"`` strings and imported only when
used (kiss-icp, gtsam and torch stay out of start-up). A library user registers
their own with a factory that takes the pipeline config::

    from flowslam.registry import register_frontend

    @register_frontend("my-icp")
    def make_my_icp(config):
        return MyIcpFrontend(...)
"""

from __future__ import annotations

import importlib
from typing import Any, Callable

from flowslam.errors import InputError

Factory = Callable[[Any], Any]

_FRONTENDS: dict[str, Factory | str] = {
    "kiss-icp": "flowslam.frontends.kiss_icp:make_frontend",
    "gt": "flowslam.frontends.ground_truth:make_gt_frontend",
    "gt-flow": "flowslam.frontends.ground_truth:make_gt_flow_frontend",
    "ssf": "flowslam.frontends.ssf:make_frontend",
    "ransac": "flowslam.frontends.ransac:make_frontend",
    "sf": "flowslam.frontends.ssf_ablations:make_sf_frontend",
    "gt-seg": "flowslam.frontends.ssf_ablations:make_gt_seg_frontend",
    "gt-flow+ssf-seg": "flowslam.frontends.ssf_ablations:make_gt_flow_ssf_seg_frontend",
}
_BACKENDS: dict[str, Factory | str] = {
    "odometry": "flowslam.backends.odometry:make_backend",
    "isam2": "flowslam.backends.isam2:make_backend",
}


def _register(table: dict, kind: str, name: str, factory: Factory | None):
    def deco(f: Factory) -> Factory:
        if name in table and table[name] is not f:
            raise ValueError(f"{kind} {name!r} is already registered")
        table[name] = f
        return f

    return deco(factory) if factory is not None else deco


def register_frontend(name: str, factory: Factory | None = None):
    """Register a frontend factory ``factory(config) -> Frontend`` (usable as a decorator)."""
    return _register(_FRONTENDS, "frontend", name, factory)


def register_backend(name: str, factory: Factory | None = None):
    """Register a backend factory ``factory(config) -> Backend`` (usable as a decorator)."""
    return _register(_BACKENDS, "backend", name, factory)


def _resolve(table: dict, kind: str, name: str) -> Factory:
    if name not in table:
        raise InputError(None, f"unknown {kind} {name!r}; available: {', '.join(sorted(table))}")
    entry = table[name]
    if isinstance(entry, str):
        module, attr = entry.split(":")
        entry = getattr(importlib.import_module(module), attr)
        table[name] = entry
    return entry


def make_frontend(name: str, config: Any):
    """Instantiate the frontend registered as ``name``."""
    return _resolve(_FRONTENDS, "frontend", name)(config)


def make_backend(name: str, config: Any):
    """Instantiate the backend registered as ``name``."""
    return _resolve(_BACKENDS, "backend", name)(config)


def frontend_names() -> list[str]:
    return sorted(_FRONTENDS)


def backend_names() -> list[str]:
    return sorted(_BACKENDS)
