"""The VPP stage's settings (controller config `vpp:`): the stage's own knobs and those of its
parts (mask memory, partition, tracking, deformable regions, belief, backend runner)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from models.vlm.runner import BackendRunnerConfig
from runtime.vpp.belief import BeliefConfig
from runtime.vpp.deformable import DeformableConfig
from runtime.vpp.mask_memory import MaskMemoryConfig
from runtime.vpp.partition.config import PartitionConfig
from runtime.vpp.tracking.config import TrackingConfig

DEFAULT_PROMPT = (
    "A small ground robot must drive to its goal through this scene. For each marked object, say "
    "whether the robot may push it or brush past it, and how costly contact would be."
)


class VppConfig(BaseModel):
    """The VPP stage's settings (controller config `vpp:`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    prompt: str = Field(DEFAULT_PROMPT, min_length=1, max_length=2000)
    #: A movable object with at least this contact cost stays in P_fix (IMPACT: 8+ is fragile).
    never_touch_cost: float = Field(8.0, ge=0.0, le=10.0)
    #: A warped mask grown to more than this many times its captured area (the camera came close
    #: to the object's plane, or the object moved: a pushed box stays in front of the robot while
    #: the warp assumes it stood still) is not trusted: its points stay P_fix. Without it a mask
    #: swells over the whole image and gates fixed objects as movable.
    max_mask_growth: float = Field(2.5, gt=1.0, le=100.0)
    #: A tracked object that moved more than this since a mask's capture: that mask is not
    #: trusted (the tracker labels the object instead); one that did not is trusted whatever its growth.
    moved_tolerance_m: float = Field(0.05, gt=0.0, le=1.0)
    #: Movable objects followed between masks (a pushed box leaves its mask): runtime/vpp/tracking/.
    tracking: TrackingConfig = TrackingConfig()
    #: Deformable objects (a curtain): the region where each hangs, not a track (runtime/vpp/deformable.py).
    deformable: DeformableConfig = DeformableConfig()
    #: The per-obstacle belief over movable / heavy / fragile (runtime.vpp.belief; BEACON).
    belief: BeliefConfig = BeliefConfig()
    #: Seconds of continuous push that give the belief one observation (ContactEvidence).
    belief_window_s: float = Field(1.0, gt=0.0, le=30.0)
    #: The controller waits for the first answer (mode dct); after this long without one it drives
    #: on what it has (every point P_fix), and says so.
    first_answer_timeout_s: float = Field(5.0, gt=0.0, le=120.0)
    memory: MaskMemoryConfig = MaskMemoryConfig()
    partition: PartitionConfig = PartitionConfig()
    runner: BackendRunnerConfig = BackendRunnerConfig()

    @model_validator(mode="after")
    def _runner_clock_is_the_controllers(self) -> "VppConfig":
        if "clock" in self.runner.model_fields_set:
            raise ValueError("vpp.runner.clock is the controller's (lockstep in the simulator, realtime on the "
                             "robot), not a setting: remove it")
        return self


__all__ = ["DEFAULT_PROMPT", "VppConfig"]
