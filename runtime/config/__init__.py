"""The controller configuration: the schema (schema.py), presets (presets.py), and reading the
shipped defaults with a user's overlay (loading.py). docs/architecture.md, section Configuration.

The names below load their module on first use, so that `from runtime.config import presets`
(the command line's choices) does not import the whole schema.
"""
from importlib import import_module

_WHERE = {
    "ConfigFileError": "calibration.errors",
    "config_sources": "runtime.config.loading",
    "load_controller_config": "runtime.config.loading",
    **{name: "runtime.config.schema" for name in (
        "ControllerConfig", "LoopConfig", "ObstaclePointsConfig", "PlannerConfig", "PurePursuitConfig",
        "SafetyStopConfig", "VppSettings", "check_against_robot")},
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module 'runtime.config' has no attribute {name!r}")
    value = getattr(import_module(_WHERE[name]), name)
    globals()[name] = value
    return value
