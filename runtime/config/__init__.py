"""The controller configuration: the schema (schema.py), presets (presets.py), and reading the
shipped defaults with a user's overlay (loading.py). docs/architecture.md, section Configuration."""
from calibration.errors import ConfigFileError
from runtime.config.loading import config_sources, load_controller_config
from runtime.config.schema import (ControllerConfig, LoopConfig, ObstaclePointsConfig, PlannerConfig,
                                   PurePursuitConfig, SafetyStopConfig, VppSettings, check_against_robot)

__all__ = ["ConfigFileError", "ControllerConfig", "LoopConfig", "ObstaclePointsConfig", "PlannerConfig",
           "PurePursuitConfig", "SafetyStopConfig", "VppSettings", "check_against_robot", "config_sources",
           "load_controller_config"]
