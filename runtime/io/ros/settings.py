"""The `ros:` section of the controller config: what the controller process reads and publishes.

Inputs are the receiver's RosInputConfig (topics, types, QoS, DDS domain). Outputs are what an
operator watches in RViz or Foxglove (runtime.io.ros.publisher): odometry, the plan, P_fix and
P_mov, and a DiagnosticArray with the state and the stage timings. The defaults are the topics
the LIMO's drivers publish (livox_ros_driver2 with xfer_format 1: CustomMsg) and the Nav2 goal
convention.
"""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from runtime.io.ros.receiver import (
    _ROS_NAME, CameraTopic, GoalTopic, ImuTopic, LidarTopic, RosInputConfig, TopicQos,
)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RosOutputConfig(_Strict):
    """Topics the controller publishes (all best effort, keep last 1: an operator's view, not data
    anything depends on). A topic set to null is not published."""

    odometry: str | None = "/dct/odom"
    plan: str | None = "/dct/plan"
    p_fix: str | None = "/dct/p_fix"
    p_mov: str | None = "/dct/p_mov"
    diagnostics: str | None = "/diagnostics"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    #: Odometry and diagnostics go out every tick; the point clouds and the plan every this many.
    clouds_every_ticks: int = Field(default=2, ge=1, le=1000)
    #: Ticks queued for the publisher thread; when it is behind, the newest waits and older ones
    #: are dropped (counted), the tick never blocks.
    queue_depth: int = Field(default=4, ge=1, le=256)

    @field_validator("odometry", "plan", "p_fix", "p_mov", "diagnostics")
    @classmethod
    def _ros_name(cls, v: str | None) -> str | None:
        if v is not None and (not _ROS_NAME.match(v) or "//" in v or v.endswith("/")):
            raise ValueError(f"{v!r} is not a ROS 2 topic name (e.g. /dct/odom)")
        return v


DEFAULT_INPUTS = RosInputConfig(
    lidar=LidarTopic(topic="/livox/lidar", type="livox_ros_driver2/msg/CustomMsg"),
    camera=CameraTopic(topic="/camera/color/image_raw", type="sensor_msgs/msg/Image", qos=TopicQos(depth=1)),
    imu=ImuTopic(topic="/livox/imu"),
    goal=GoalTopic(),
)


class RosConfig(_Strict):
    inputs: RosInputConfig = DEFAULT_INPUTS
    outputs: RosOutputConfig = RosOutputConfig()

    @model_validator(mode="after")
    def _workspace_frame(self) -> "RosConfig":
        ws = self.inputs.goal.workspace if self.inputs.goal is not None else None
        if ws is not None and ws.frame == "odom" and self.outputs.odom_frame != "odom":
            raise ValueError(f"inputs.goal.workspace.frame odom is not the odometry frame "
                             f"(outputs.odom_frame {self.outputs.odom_frame!r})")
        return self


__all__ = ["RosConfig", "RosOutputConfig", "DEFAULT_INPUTS"]
