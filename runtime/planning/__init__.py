"""Planning stage: reference path (A* on a local grid), point selection, the OSQP MPC."""
from runtime.planning.distance_model import DistanceModel, ExactRectangleDual
from runtime.planning.errors import DistanceModelError, PlannerInputError
from runtime.planning.mpc import MpcPlanner, PlanResult
from runtime.planning.mpc_config import MpcConfig, MpcWeights
from runtime.planning.point_selection import PointSelectionConfig, PointSelector, SelectedPoints
from runtime.planning.reference_path import ReferencePathConfig, ReferencePathPlanner, ReferenceUpdate

__all__ = [
    "DistanceModel", "ExactRectangleDual", "DistanceModelError", "PlannerInputError",
    "MpcConfig", "MpcPlanner", "MpcWeights", "PlanResult", "PointSelectionConfig",
    "PointSelector", "SelectedPoints", "ReferencePathConfig", "ReferencePathPlanner", "ReferenceUpdate",
]
