"""The base of every configuration model: strict keys, field docstrings as descriptions.

This layer imports only pydantic (and the standard library): algorithms import their
options from here, never the reverse, so loading or printing a configuration never
imports torch, GTSAM, Open3D or kiss-icp.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictModel(BaseModel):
    """A configuration section: unknown keys are errors; NaN and infinity are refused in
    every float field; the docstring written under a field becomes its description
    (shown by ``flowslam config``)."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True, allow_inf_nan=False)
