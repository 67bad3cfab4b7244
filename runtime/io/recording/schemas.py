"""The JSON schemas of the recorded channels (MCAP `jsonschema` encoding, JSON messages).

JSON rather than ROS 2 CDR: Foxglove opens jsonschema channels with no plug-in, the writer needs no
message compiler, and `json.loads` is all a reader needs. The pose, point cloud and path channels
use Foxglove's well-known schema names and shapes (foxglove.PoseInFrame, foxglove.PointCloud,
foxglove.PosesInFrame) so the 3D panel draws them; the rest are ours (`dct.*`) and plot as fields.
"""
from __future__ import annotations

import json

from runtime.io.recording import backend_answers as BA

TOPIC_TICK = "/dct/tick"
TOPIC_POSE = "/dct/pose"
TOPIC_CAN = "/dct/can"
TOPIC_PARTITION = "/dct/partition"
TOPIC_P_FIX = "/dct/p_fix"
TOPIC_PLAN = "/dct/plan"
TOPIC_REFERENCE = "/dct/reference_path"
TOPIC_VPP_ANSWER = "/dct/vpp/answer"
TOPIC_VPP_MASKS = "/dct/vpp/masks"
TOPIC_THREADS = "/dct/threads"
TOPIC_INPUTS = "/dct/inputs"

#: Metadata record names: the run (written first, so a cut-off file keeps it) and the recorder's
#: own account (written at the end: records written and dropped).
META_RUN = "dct.run"
META_RECORDING = "dct.recording"
#: A `dct.run` key: how the ticks' now_s (/dct/inputs) were recorded. TICK_NOW_OWN: each is its
#: tick's own clock reading. Recordings without the key may carry, for the tick a deadline stop
#: came after, the stop verdict's time instead (runtime.app.replay.source._tick_now).
META_TICK_NOW = "tick_now"
TICK_NOW_OWN = "own"

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_TIME = {
    "type": "object",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VEC3 = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
_QUAT = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}}


def tick_schema(stages: tuple[str, ...]) -> dict:
    """One record of the telemetry ring buffer (runtime.loop.telemetry.tick_record_dtype), in ms."""
    return {
        "title": "dct.Tick",
        "description": "One control tick: stage durations (wall clock), lateness, deadline flags, state, command.",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "tick": {"type": "integer"},
            "scheduled_s": _NUM,
            "lateness_ms": _NUM,
            "stage_ms": {"type": "object", "properties": {s: _NUM for s in stages}},
            "tick_ms": _NUM,
            "slack_work_ms": _NUM,
            "command_latency_ms": {**_NUM, "description": "scheduled start -> command written, loop clock"},
            "overrun_stages": {"type": "array", "items": {"type": "string"}},
            "deadline_missed": {"type": "boolean"},
            "wall_command_latency_ms": _NUM,
            "wall_deadline_missed": {"type": "boolean"},
            "state": {"type": "string"},
            "reason": {"type": ["string", "null"],
                       "description": "why the robot is held (HOLDING: the faulty inputs) or stopped (STOPPED); "
                                      "null otherwise"},
            "v_cmd_mps": _NUM,
            "omega_cmd_radps": _NUM,
            "lidar_frame_stamp_s": {**_NUM_OR_NULL, "description": "start of the lidar frame this tick used (null: none)"},
            "lidar_frame_end_s": {**_NUM_OR_NULL, "description": "end of the lidar frame this tick used (null: none)"},
            "sensor_to_command_ms": {**_NUM_OR_NULL, "description": "lidar frame end -> this tick's command"},
            "command_written_at_ms": {**_NUM_OR_NULL, "description": "wall clock, tick start -> the command "
                                                                     "written (null: none written)"},
            "slack_work_start_at_ms": {**_NUM_OR_NULL, "description": "wall clock, tick start -> the slack work's "
                                                                      "start (null: none ran)"},
        },
    }


POSE_IN_FRAME = {
    "title": "foxglove.PoseInFrame",
    "type": "object",
    "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
}

POSES_IN_FRAME = {
    "title": "foxglove.PosesInFrame",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "poses": {"type": "array", "items": _POSE},
    },
}

POINT_CLOUD = {
    "title": "foxglove.PointCloud",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _POSE,
        "point_stride": {"type": "integer", "minimum": 0},
        "fields": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "offset": {"type": "integer", "minimum": 0},
                    "type": {"type": "integer", "description": "foxglove NumericType (7 = FLOAT32)"},
                },
            },
        },
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}

CAN_FRAME = {
    "title": "dct.CanFrame",
    "description": "A CAN frame the controller sent (tx) or received (rx), stamped on the loop clock.",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "direction": {"type": "string", "enum": ["tx", "rx"]},
        "id": {"type": "integer"},
        "id_hex": {"type": "string"},
        "dlc": {"type": "integer"},
        "data_hex": {"type": "string"},
        "send_us": {**_NUM_OR_NULL, "description": "wall-clock microseconds send() took (null: received)"},
    },
}

PARTITION = {
    "title": "dct.Partition",
    "description": "Point counts at a lower rate: lidar returns, P_fix (constrains the planner), P_mov (movable).",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "tick": {"type": "integer"},
        "lidar_returns": {"type": "integer"},
        "p_fix": {"type": "integer"},
        "p_mov": {"type": ["integer", "null"]},
    },
}

VPP_ANSWER = {
    "title": "dct.VppAnswer",
    "description": "A VLM answer the VPP mask memory applied: when it arrived (the tick that applied it), the "
                   "capture stamp of the image it answered, the latency between them, and its objects.",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "arrival_s": {**_NUM, "description": "scheduled start of the tick that applied the answer (loop clock)"},
        "capture_s": {**_NUM, "description": "capture stamp of the image the answer is about"},
        "latency_ms": {**_NUM, "description": "image capture -> the masks in the controller"},
        "answers": {"type": "integer", "description": "answers the VPP stage received so far (failed ones included)"},
        "objects": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "object_id": {"type": "integer"},
                    "label": {"type": "string"},
                    "movable": {"type": "boolean"},
                    "contact_cost": _NUM,
                    "pixels": {"type": "integer", "description": "pixels in the mask at capture resolution"},
                },
            },
        },
    },
}

COMPRESSED_IMAGE = {
    "title": "foxglove.CompressedImage",
    "description": "The answer's masks as one label image, coloured by contact cost (green 0 .. red 10), downscaled.",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}

THREADS = {
    "title": "dct.Threads",
    "description": "CPU time (user + system, since each thread started) of every live Python thread, sampled "
                   "about once a second of wall time by the recorder's writer thread.",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "wall_s": {**_NUM, "description": "wall-clock seconds since the recorder started"},
        "process_cpu_s": {**_NUM, "description": "the whole process's CPU time (all threads, Python or not)"},
        "queue": {"type": "integer", "description": "records waiting in the recorder's queue for the writer"},
        "rss_mb": {**_NUM, "description": "the process's resident memory (MiB; absent where there is no /proc)"},
        "open_fds": {"type": "integer", "description": "the process's open file descriptors (absent without /proc)"},
        "threads": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"name": {"type": "string"}, "tid": {"type": "integer"}, "cpu_s": _NUM},
            },
        },
    },
}

TICK_INPUTS = {
    "title": "dct.TickInputs",
    "description": "What one tick took in, for `dct replay`: the controller's clock at the tick, how many sensor "
                   "samples had reached it (the raw channels' sequence numbers up to this one), the ICP results "
                   "it received, and its goal.",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "tick": {"type": "integer"},
        "scheduled_s": _NUM,
        "now_s": {**_NUM, "description": "the controller's clock when the tick started (its `now`)"},
        "sensor_samples": {"type": "integer", "minimum": 0,
                           "description": "sensor samples (lidar, camera, IMU) that had reached the controller"},
        "icp_results": {
            "type": "array",
            "description": "the ICP results this tick received: the job's number, its frame's stamp and end, "
                           "the worker's compute time (wall clock), whether the registration failed",
            "items": {"type": "object", "properties": {"seq": {"type": "integer"}, "stamp_s": _NUM, "end_s": _NUM,
                                                       "compute_ms": _NUM, "failed": {"type": "boolean"}}},
        },
        "goal": {"type": "object", "properties": {"x": _NUM, "y": _NUM, "yaw": _NUM},
                 "description": "the controller's goal in the odometry frame"},
    },
}

#: topic -> (schema name, schema); the tick schema depends on the stage names.
def channel_schemas(stages: tuple[str, ...]) -> dict[str, tuple[str, dict]]:
    return {
        TOPIC_TICK: ("dct.Tick", tick_schema(stages)),
        TOPIC_POSE: ("foxglove.PoseInFrame", POSE_IN_FRAME),
        TOPIC_CAN: ("dct.CanFrame", CAN_FRAME),
        TOPIC_PARTITION: ("dct.Partition", PARTITION),
        TOPIC_P_FIX: ("foxglove.PointCloud", POINT_CLOUD),
        TOPIC_PLAN: ("foxglove.PosesInFrame", POSES_IN_FRAME),
        TOPIC_REFERENCE: ("foxglove.PosesInFrame", POSES_IN_FRAME),
        TOPIC_VPP_ANSWER: ("dct.VppAnswer", VPP_ANSWER),
        TOPIC_VPP_MASKS: ("foxglove.CompressedImage", COMPRESSED_IMAGE),
        TOPIC_THREADS: ("dct.Threads", THREADS),
        TOPIC_INPUTS: ("dct.TickInputs", TICK_INPUTS),
        BA.TOPIC: (BA.SCHEMA["title"], BA.SCHEMA),
    }


def schema_bytes(schema: dict) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()
