"""The `ros:` section of the controller config: what the controller process reads and publishes.

Inputs are the receiver's RosInputConfig (topics, types, QoS, DDS domain). Outputs are what an
operator watches in RViz or Foxglove (runtime.io.ros.publisher): odometry, the plan, P_fix and
P_mov, and a DiagnosticArray with the state and the stage timings. The defaults are the topics
the LIMO's drivers publish (livox_ros_driver2 with xfer_format 1: CustomMsg) and the Nav2 goal
convention.
"""
from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from runtime.io.ros.receiver import (
    _ROS_NAME, CameraInfoTopic, CameraTopic, GoalTopic, ImuTopic, LidarTopic, RosInputConfig, TopicQos,
)
from runtime.io.ros.transport import TransportOptions


_FRAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_/]*$")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RosOutputConfig(_Strict):
    """Topics and frames the controller publishes (runtime.io.ros.publisher). A topic set to null
    is not published. Names and QoS follow REP-105 and Nav2's conventions (docs/ros.md)."""

    odometry: str | None = "/dct/odom"
    plan: str | None = "/dct/plan"
    p_fix: str | None = "/dct/p_fix"
    p_mov: str | None = "/dct/p_mov"
    diagnostics: str | None = "/diagnostics"
    #: The safety supervisor's footprint, stop and slow zones (visualization_msgs/MarkerArray).
    safety_markers: str | None = "/dct/safety_markers"
    #: odom -> base_link on /tf every tick, and base_link -> lidar / camera once on /tf_static.
    publish_tf: bool = True
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    #: The sensors' frames as their drivers stamp them (livox_ros_driver2's default; a ROS camera
    #: driver's optical frame): the children of base_link on /tf_static.
    lidar_frame: str = "livox_frame"
    camera_frame: str = "camera_color_optical_frame"
    #: Odometry, /tf and diagnostics go out every tick; the point clouds, the plan and the
    #: markers every this many.
    clouds_every_ticks: int = Field(default=2, ge=1, le=1000)
    #: Ticks queued for the publisher thread; when it is behind, the newest waits and older ones
    #: are dropped (counted), the tick never blocks.
    queue_depth: int = Field(default=4, ge=1, le=256)

    @field_validator("odometry", "plan", "p_fix", "p_mov", "diagnostics", "safety_markers")
    @classmethod
    def _ros_name(cls, v: str | None) -> str | None:
        if v is not None and (not _ROS_NAME.match(v) or "//" in v or v.endswith("/")):
            raise ValueError(f"{v!r} is not a ROS 2 topic name (e.g. /dct/odom)")
        return v

    @field_validator("odom_frame", "base_frame", "lidar_frame", "camera_frame")
    @classmethod
    def _frame_name(cls, v: str) -> str:
        if not _FRAME.match(v):
            raise ValueError(f"{v!r} is not a tf2 frame name (letters, digits, _ and /, no leading /)")
        return v


DEFAULT_INPUTS = RosInputConfig(
    lidar=LidarTopic(topic="/livox/lidar", type="livox_ros_driver2/msg/CustomMsg"),
    camera=CameraTopic(topic="/camera/color/image_raw", type="sensor_msgs/msg/Image", qos=TopicQos(depth=1)),
    camera_info=CameraInfoTopic(topic="/camera/color/camera_info"),
    imu=ImuTopic(topic="/livox/imu"),
    goal=GoalTopic(),
)


class RosSecurity(_Strict):
    """SROS2: the node runs with this keystore's enclave (rclpy and a ROS 2 built with DDS Security)."""

    keystore: str
    enclave: str = "/dct_controller"


class RosConfig(_Strict):
    #: auto: rclpy when it imports (a robot with ROS 2 installed), else cyclonedds
    #: (runtime.io.ros.transport).
    middleware: Literal["auto", "rclpy", "cyclonedds"] = "auto"
    #: subnet: ROS 2's default, every host on the network; localhost: this machine only.
    discovery: Literal["subnet", "localhost"] = "subnet"
    security: RosSecurity | None = None
    inputs: RosInputConfig = DEFAULT_INPUTS
    outputs: RosOutputConfig = RosOutputConfig()

    def transport_options(self, node_name: str = "dct_controller") -> TransportOptions:
        sec = self.security
        return TransportOptions(middleware=self.middleware, domain_id=self.inputs.domain_id,
                                discovery=self.discovery, node_name=node_name,
                                security_keystore=sec.keystore if sec else None,
                                security_enclave=sec.enclave if sec else None)

    @model_validator(mode="after")
    def _workspace_frame(self) -> "RosConfig":
        ws = self.inputs.goal.workspace if self.inputs.goal is not None else None
        if ws is not None and ws.frame == "odom" and self.outputs.odom_frame != "odom":
            raise ValueError(f"inputs.goal.workspace.frame odom is not the odometry frame "
                             f"(outputs.odom_frame {self.outputs.odom_frame!r})")
        return self


__all__ = ["RosConfig", "RosOutputConfig", "RosSecurity", "DEFAULT_INPUTS"]
