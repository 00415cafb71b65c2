"""The run configuration (``PipelineConfig``): one YAML file, one section per part.

``flowslam config`` prints the defaults with every field's description as a comment;
``flowslam run --config FILE`` loads a file (any subset of keys); command-line options
override the file. ``flowslam train --config FILE`` reads the ``training:`` section of
the same file. Units: metres, seconds, radians -- except fields whose name says ``_deg``.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import BaseModel, ValidationError

from flowslam.config.adapt import AdaptConfig
from flowslam.config.base import StrictModel
from flowslam.config.baselines import RansacConfig
from flowslam.config.dataset import DatasetConfig
from flowslam.config.isam2 import Isam2Config
from flowslam.config.loop_closure import LoopClosureConfig
from flowslam.config.mapping import MappingConfig
from flowslam.config.odometry import FlowOdometryConfig, KissIcpConfig
from flowslam.config.output import OutputConfig
from flowslam.config.ssf import SsfConfig
from flowslam.config.training import TrainConfig
from flowslam.errors import InputError


class PipelineConfig(StrictModel):
    """A flowslam run: which frontend and backend, and the options of every part."""

    frontend: str = "kiss-icp"
    """Frontend name (``flowslam plugins`` lists them)."""
    backend: str = "odometry"
    """Backend name: 'odometry' (chain, no optimisation) or 'isam2'."""
    output_dir: Path = Path("results")
    """Run folders go here, each ``<date>_<time>_<tag>`` with ``latest`` pointing at the newest."""
    dataset: DatasetConfig = DatasetConfig()
    """Reader and frame range."""
    output: OutputConfig = OutputConfig()
    """Optional outputs of a run."""
    kiss_icp: KissIcpConfig = KissIcpConfig()
    """The ``kiss-icp`` frontend."""
    ransac: RansacConfig = RansacConfig()
    """The ``ransac`` frontend (FPFH + RANSAC global registration, SSF-PAN's baseline)."""
    flow_odometry: FlowOdometryConfig = FlowOdometryConfig()
    """Flow pairs -> relative pose, for every flow frontend (``ssf``, ``gt``, ``gt-flow``)."""
    ssf: SsfConfig = SsfConfig()
    """The ``ssf`` frontend, stage by stage."""
    isam2: Isam2Config = Isam2Config()
    """The ``isam2`` backend."""
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    """Loop detection for backends that take loops (``enabled``: s-loam, off: a-loam)."""
    mapping: MappingConfig = MappingConfig()
    """Scan-to-map registration (LOAM's mapping stage) for backends with factors (``isam2``)."""
    training: TrainConfig = TrainConfig()
    """``flowslam train``: training the scene-flow network."""
    adapt: AdaptConfig = AdaptConfig()
    """``flowslam adapt``: self-supervised fine-tuning of the network on unlabelled sequences."""

    @property
    def variant(self) -> str:
        """'s-loam' when loop closure is on, 'a-loam' otherwise (isam2's naming)."""
        return "s-loam" if self.loop_closure.enabled else "a-loam"


VARIANTS = {"a-loam": False, "s-loam": True}
"""``--variant`` names and the ``loop_closure.enabled`` each stands for."""


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise InputError(path, "config file does not exist") from None
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read config: {e}".splitlines()[0]) from None
    if not isinstance(data, dict):
        raise InputError(path, "config must be a YAML mapping")
    return data


def set_dotted(data: dict, overrides: dict) -> None:
    """Set each non-None value of ``overrides`` (dotted names for nested fields, e.g.
    ``{"ssf.network.max_points": 8192}``) in the nested mapping ``data``, in place."""
    for dotted, value in overrides.items():
        if value is None:
            continue
        node = data
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value


def validated(model: type[BaseModel], data: dict, path: Path | None):
    """``model.model_validate(data)``; a validation error becomes one ``InputError`` line
    naming the file and the first bad field."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise InputError(path, f"config field {where!r}: {err['msg']}") from None


def load_config(path: Path | None = None, **overrides) -> PipelineConfig:
    """Defaults, updated from a YAML file (if given), then from non-None ``overrides``.

    Overrides use dotted names for nested fields, e.g. ``{"dataset.topic": "/points"}``;
    ``variant="a-loam"`` / ``"s-loam"`` sets ``loop_closure.enabled``.
    """
    data: dict = {}
    if path is not None:
        path = Path(path)
        data = _read_yaml(path)
    variant = overrides.pop("variant", None)
    if variant is not None:
        if variant not in VARIANTS:
            raise InputError(None, f"unknown variant {variant!r}; choose a-loam or s-loam")
        overrides["loop_closure.enabled"] = VARIANTS[variant]
    set_dotted(data, overrides)
    return validated(PipelineConfig, data, path)


def load_training_config(path: Path | None = None, **overrides) -> TrainConfig:
    """The ``training:`` section of a run config file (YAML), or a bare ``TrainConfig``
    file (YAML or JSON: a mapping of its fields), updated from non-None ``overrides``."""
    data: dict = {}
    if path is not None:
        path = Path(path)
        data = _read_yaml(path)
        if "training" in data:
            data = data["training"] or {}
        elif set(data) & (set(PipelineConfig.model_fields) - set(TrainConfig.model_fields)):
            data = {}  # a run config without a training section: the defaults
    set_dotted(data, overrides)
    return validated(TrainConfig, data, path)
