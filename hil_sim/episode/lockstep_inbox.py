"""The controller's sensor inbox in a lockstep episode: a SensorInbox whose producers may finish
a due delivery just before the controller reads it.

The simulated camera renders beside the physics (hil_sim.world.sensor_rig.CameraThread) and its
image is due a fixed simulated latency after its instant. Handing it over in the physics step at
that instant would make the physics wait for the render there; the controller reads its inbox
only in its tick (`take`), so the rig hands it over just before that read instead
(`SensorRig.defer_hand_over`). The controller finds exactly what it would have found, in the same
order (the delivery point is fixed, never "when the render happened to finish": the run stays
deterministic), and the physics runs on beside the render meanwhile.
"""
from __future__ import annotations

from typing import Callable

from runtime.io.sensor_inbox import SensorInbox, SensorSnapshot


class LockstepInbox(SensorInbox):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        #: Called, in order, before every take: each hands over what it has due.
        self.before_take: list[Callable[[], None]] = []

    def take(self) -> SensorSnapshot:
        for hand_over in self.before_take:
            hand_over()
        return super().take()


__all__ = ["LockstepInbox"]
