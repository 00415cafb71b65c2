"""Configuration: the floor of flowslam's layers (imports only pydantic and PyYAML).

Every option of a run lives here, one module per part; algorithms import their section
from here, never the reverse. ``PipelineConfig`` holds them all (one YAML file):

- ``dataset`` (:mod:`.dataset`), ``output`` (:mod:`.output`);
- ``kiss_icp`` and ``flow_odometry`` (:mod:`.odometry`);
- ``ssf`` with one section per stage (:mod:`.ssf`);
- ``isam2`` (:mod:`.isam2`), ``loop_closure`` (:mod:`.loop_closure`) and ``mapping``
  (:mod:`.mapping`);
- ``training`` (:mod:`.training`) and ``adapt`` (:mod:`.adapt`).
"""

from flowslam.config.adapt import AdaptConfig, AdaptLossWeights
from flowslam.config.baselines import RansacConfig
from flowslam.config.dataset import DatasetConfig
from flowslam.config.describe import dump_config, missing_descriptions
from flowslam.config.isam2 import Isam2Config
from flowslam.config.loop_closure import LoopClosureConfig, ScanContextConfig, VerificationConfig
from flowslam.config.mapping import MappingConfig
from flowslam.config.odometry import FlowOdometryConfig, KissIcpConfig
from flowslam.config.output import OutputConfig
from flowslam.config.pipeline import VARIANTS, PipelineConfig, load_config, load_training_config, set_dotted
from flowslam.config.ssf import (
    FlowRefinementConfig, MotionEvidenceConfig, NetworkStageConfig, ObjectRefinementConfig,
    PoseStartConfig, SsfConfig,
)
from flowslam.config.training import PriorNoise, TrainConfig

__all__ = [
    "AdaptConfig", "AdaptLossWeights", "DatasetConfig", "FlowOdometryConfig", "FlowRefinementConfig", "Isam2Config", "KissIcpConfig",
    "LoopClosureConfig", "MappingConfig", "MotionEvidenceConfig", "NetworkStageConfig", "ObjectRefinementConfig",
    "OutputConfig", "PipelineConfig", "PoseStartConfig", "PriorNoise", "RansacConfig", "ScanContextConfig",
    "SsfConfig", "TrainConfig", "VARIANTS", "VerificationConfig", "dump_config", "load_config",
    "load_training_config", "missing_descriptions", "set_dotted",
]
