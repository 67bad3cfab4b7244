"""PointCloud2 -> LidarScan with per-point times found from the driver's fields, and the Livox
driver's PointCloud2 layout out: runtime/io/ros/pointcloud.py (through convert.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.io.ros import convert as C
from runtime.io.ros import messages as M
from tests.runtime.io.test_ros_convert import rejects

_NUMPY_OF = {M.INT8: "i1", M.UINT8: "u1", M.INT16: "i2", M.UINT16: "u2", M.INT32: "i4", M.UINT32: "u4",
             M.FLOAT32: "f4", M.FLOAT64: "f8"}
STAMP_NS = 1_700_000_000_250_000_000       # a 2023 ROS time


def cloud(columns: dict, *, offsets: dict | None = None, point_step: int | None = None, big_endian=False,
          height=1, row_pad=0, is_dense=True, stamp_ns=STAMP_NS, frame="lidar"):
    """A PointCloud2 whose fields are `columns` ({name: (datatype, values)}), packed in that order
    unless `offsets` places them, with the given point_step, endianness and row padding."""
    e = ">" if big_endian else "<"
    names = list(columns)
    if offsets is None:
        offsets, off = {}, 0
        for k in names:
            offsets[k] = off
            off += np.dtype(_NUMPY_OF[columns[k][0]]).itemsize
    step = point_step or max(offsets[k] + np.dtype(_NUMPY_OF[columns[k][0]]).itemsize for k in names)
    n = len(next(iter(columns.values()))[1])
    rec = np.zeros(n, dtype={"names": names, "formats": [e + _NUMPY_OF[columns[k][0]] for k in names],
                             "offsets": [offsets[k] for k in names], "itemsize": step})
    for k in names:
        rec[k] = columns[k][1]
    width = n // height
    rows, row_bytes = rec.tobytes(), width * step
    data = b"".join(rows[r * row_bytes:(r + 1) * row_bytes] + b"\xab" * row_pad for r in range(height))
    fields = [M.PointField(k, offsets[k], columns[k][0], 1) for k in names]
    header = M.Header(M.Time(stamp_ns // 10**9, stamp_ns % 10**9), frame)
    return M.PointCloud2(header, height, width, fields, big_endian, step, row_bytes + row_pad, data, is_dense)


def xyz_columns(xyz, datatype=M.FLOAT32):
    return {"x": (datatype, xyz[:, 0]), "y": (datatype, xyz[:, 1]), "z": (datatype, xyz[:, 2])}


def point_times(scan):
    """Each point's absolute time (s) as the scan says."""
    return scan.stamp_s + scan.point_time_offsets_s.astype(np.float64)


# What each per-point time encoding writes, given the header stamp (ns) and each point's time after it (s):
# (field, datatype, encode(stamp_ns, rel_s), config for an explicit time_field, auto finds it)
ENCODINGS = {
    "livox_ns": ("timestamp", M.FLOAT64, lambda s, r: (s + np.round(r * 1e9).astype(np.int64)).astype(np.float64),
                 dict(time_unit_s=1e-9, time_is_absolute=True), True),
    "hesai_s": ("timestamp", M.FLOAT64, lambda s, r: s * 1e-9 + r, dict(time_is_absolute=True), True),
    "ouster_t": ("t", M.UINT32, lambda s, r: np.round(r * 1e9), dict(time_unit_s=1e-9), True),
    "offset_time": ("offset_time", M.UINT32, lambda s, r: np.round(r * 1e9), dict(time_unit_s=1e-9), True),
    "velodyne_f32": ("time", M.FLOAT32, lambda s, r: r, {}, True),
    "time_f64": ("time", M.FLOAT64, lambda s, r: r, {}, True),
    "custom_us": ("stamp_us", M.INT32, lambda s, r: np.round(r * 1e6), dict(time_unit_s=1e-6), False),
    "custom_abs_ms": ("t_ms", M.FLOAT64, lambda s, r: s * 1e-6 + r * 1e3, dict(time_unit_s=1e-3, time_is_absolute=True),
                      False),
}
# the time quantum of each encoding (s), for the comparisons (float32 of a 0.1 s offset: 7.5e-9)
_QUANTUM = {"livox_ns": 1e-6, "hesai_s": 1e-6, "ouster_t": 1e-6, "offset_time": 1e-6, "velodyne_f32": 1e-6,
            "time_f64": 1e-6, "custom_us": 2e-6, "custom_abs_ms": 1e-6}


@settings(max_examples=120, deadline=None)
@given(n=st.integers(1, 30), height=st.sampled_from([1, 2, 3]), encoding=st.sampled_from(sorted(ENCODINGS)),
       xyz_type=st.sampled_from([M.FLOAT32, M.FLOAT64]), big_endian=st.booleans(), row_pad=st.integers(0, 9),
       gap=st.integers(0, 6), order_seed=st.integers(0, 2**31), shift=st.floats(-0.1, 0.02),
       extra=st.lists(st.tuples(st.sampled_from(["intensity", "ring", "tag", "reflectivity"]),
                                st.sampled_from(sorted(_NUMPY_OF))), unique_by=lambda t: t[0], max_size=3),
       nan_rows=st.integers(0, 3), seed=st.integers(0, 2**31))
def test_any_layout_and_time_field_gives_the_points_and_their_times(
        n, height, encoding, xyz_type, big_endian, row_pad, gap, order_seed, shift, extra, nan_rows, seed):
    """Random field order, gaps, point_step, endianness, row padding, organised clouds, invalid
    (NaN) rows in a non-dense cloud, and every time encoding: auto and the explicit config agree,
    and every valid point comes through with its time."""
    n *= height
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-40, 40, (n, 3)).astype(np.float32)
    rel = np.sort(rng.uniform(0.0, 0.1, n)) + shift           # shift < 0: a driver that stamps the frame's end
    if ENCODINGS[encoding][1] == M.UINT32 or encoding == "custom_us":
        rel = rel - min(rel.min(), 0.0)                          # unsigned (or ns-counting) fields start at the stamp
    invalid = rng.permutation(n)[:min(nan_rows, n - 1)]
    xyz[invalid] = np.nan
    name, dtype, encode, explicit, found = ENCODINGS[encoding]
    columns = {**xyz_columns(xyz, xyz_type), name: (dtype, encode(STAMP_NS, rel))}
    for k, dt in extra:
        columns[k] = (dt, rng.integers(0, 100, n))
    names = list(columns)
    rng2 = np.random.default_rng(order_seed)
    names = [names[i] for i in rng2.permutation(len(names))]
    offsets, off = {}, 0
    for k in names:
        offsets[k] = off
        off += np.dtype(_NUMPY_OF[columns[k][0]]).itemsize + gap
    msg = cloud({k: columns[k] for k in names}, offsets=offsets, point_step=off + int(rng2.integers(0, 8)),
                big_endian=big_endian, height=height, row_pad=row_pad, is_dense=nan_rows == 0)
    msg = M.from_cdr(M.PointCloud2, M.to_cdr(msg))              # as it comes off the wire
    valid = np.isfinite(xyz).all(axis=1)
    want_t = STAMP_NS * 1e-9 + rel[valid]
    scans = [C.pointcloud2_decode(msg, time_field=name, **explicit)]
    if found:
        scans.append(C.pointcloud2_decode(msg))
    for scan, source in scans:
        np.testing.assert_array_equal(scan.points_m, xyz[valid])
        assert source is not None and source.field == name
        np.testing.assert_allclose(point_times(scan) - STAMP_NS * 1e-9, want_t - STAMP_NS * 1e-9, rtol=0,
                                   atol=_QUANTUM[encoding])
        assert scan.point_time_offsets_s.min() == 0.0
        assert scan.frame_duration_s == pytest.approx(max(0.1, rel[valid].max() - rel[valid].min()), abs=2e-6)
    untimed = C.pointcloud2_to_scan(msg, time_field="none")
    assert not untimed.point_time_offsets_s.any() and untimed.stamp_s == STAMP_NS * 1e-9


def test_livox_units_told_apart_from_hesai_by_magnitude():
    xyz = np.random.default_rng(1).uniform(-5, 5, (50, 3)).astype(np.float32)
    rel = np.linspace(0, 0.099, 50)
    for encoding, unit in (("livox_ns", 1e-9), ("hesai_s", 1.0)):
        name, dtype, encode, _, _ = ENCODINGS[encoding]
        _, source = C.pointcloud2_decode(cloud({**xyz_columns(xyz), name: (dtype, encode(STAMP_NS, rel))}))
        assert source == C.PointTime("timestamp", unit, True, auto=True)


# ----------------------------------------------------------------------------- clouds as each driver lays them out


def _frame(n=400, seed=2):
    rng = np.random.default_rng(seed)
    return rng.uniform(-20, 20, (n, 3)).astype(np.float32), np.sort(rng.uniform(0, 0.1, n))


def test_livox_ros_driver2_xfer_format_0():
    """livox_ros_driver2's PointCloud2: packed 26-byte points, timestamp FLOAT64 absolute ns at 18,
    the header stamp the first point's time."""
    xyz, rel = _frame()
    rel -= rel[0]
    offsets = {"x": 0, "y": 4, "z": 8, "intensity": 12, "tag": 16, "line": 17, "timestamp": 18}
    cols = {**xyz_columns(xyz), "intensity": (M.FLOAT32, np.full(len(xyz), 40.0)), "tag": (M.UINT8, 0x10),
            "line": (M.UINT8, np.arange(len(xyz)) % 4),
            "timestamp": (M.FLOAT64, (STAMP_NS + np.round(rel * 1e9)).astype(np.float64))}
    msg = cloud(cols, offsets=offsets, point_step=26)
    scan, source = C.pointcloud2_decode(msg)
    assert source == C.PointTime("timestamp", 1e-9, True, auto=True)
    assert scan.stamp_s == pytest.approx(STAMP_NS * 1e-9, abs=1e-6)
    np.testing.assert_allclose(scan.point_time_offsets_s, rel, atol=1e-6)
    # the encoder the simulator publishes with writes exactly this layout
    enc = C.livox_pointcloud2_msg(STAMP_NS, "livox_frame", xyz, rel)
    assert [(f.name, f.offset, f.datatype, f.count) for f in enc.fields] == \
        [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    assert (enc.point_step, enc.row_step, enc.height, enc.is_bigendian, enc.is_dense) == (26, 26 * 400, 1, False, True)
    assert (enc.header.stamp.sec, enc.header.stamp.nanosec) == (STAMP_NS // 10**9, STAMP_NS % 10**9)


def test_ouster_t_uint32_ns_relative():
    """ouster-ros: 48-byte points, x y z at 0 4 8, intensity 16, t UINT32 ns 20, reflectivity 24,
    ring 26, ambient 28, range 32; an organised cloud (a row per beam)."""
    xyz, rel = _frame(n=4 * 64)
    offsets = {"x": 0, "y": 4, "z": 8, "intensity": 16, "t": 20, "reflectivity": 24, "ring": 26, "ambient": 28,
               "range": 32}
    cols = {**xyz_columns(xyz), "intensity": (M.FLOAT32, 1.0), "t": (M.UINT32, np.round(rel * 1e9)),
            "reflectivity": (M.UINT16, 7), "ring": (M.UINT16, 1), "ambient": (M.UINT16, 2), "range": (M.UINT32, 3000)}
    scan, source = C.pointcloud2_decode(cloud(cols, offsets=offsets, point_step=48, height=4))
    assert source == C.PointTime("t", 1e-9, False, auto=True)
    np.testing.assert_allclose(point_times(scan) - STAMP_NS * 1e-9, rel, atol=1e-6)


def test_velodyne_time_float32_seconds_relative_to_the_frame_end():
    """velodyne_pointcloud: x y z intensity FLOAT32, ring UINT16 at 16, time FLOAT32 s at 18 (22
    bytes), negative when the header stamps the end of the sweep."""
    xyz, rel = _frame()
    rel -= rel[-1]
    cols = {**xyz_columns(xyz), "intensity": (M.FLOAT32, 5.0), "ring": (M.UINT16, 3), "time": (M.FLOAT32, rel)}
    msg = cloud(cols)
    assert msg.point_step == 22
    scan, source = C.pointcloud2_decode(msg)
    assert source == C.PointTime("time", 1.0, False, auto=True)
    assert scan.stamp_s == pytest.approx(STAMP_NS * 1e-9 + rel[0], abs=1e-6)
    np.testing.assert_allclose(point_times(scan) - STAMP_NS * 1e-9, rel, atol=1e-6)


def test_hesai_timestamp_float64_absolute_seconds_not_dense():
    """HesaiLidar_ROS_2.0: x y z intensity FLOAT32, ring UINT16 at 16, timestamp FLOAT64 absolute s
    at 18 (26 bytes), is_dense false with NaN points."""
    xyz, rel = _frame()
    xyz[::7] = np.nan
    cols = {**xyz_columns(xyz), "intensity": (M.FLOAT32, 5.0), "ring": (M.UINT16, 3),
            "timestamp": (M.FLOAT64, STAMP_NS * 1e-9 + rel)}
    msg = cloud(cols, is_dense=False)
    assert msg.fields[-1].offset == 18 and msg.point_step == 26
    scan, source = C.pointcloud2_decode(msg)
    assert source == C.PointTime("timestamp", 1.0, True, auto=True)
    keep = np.isfinite(xyz).all(axis=1)
    np.testing.assert_allclose(point_times(scan) - STAMP_NS * 1e-9, rel[keep], atol=1e-6)


def test_no_time_field_every_point_at_the_stamp_and_a_notice():
    xyz, _ = _frame()
    msg = cloud({**xyz_columns(xyz), "intensity": (M.FLOAT32, 1.0)}, frame="livox_frame")
    scan, source = C.pointcloud2_decode(msg)
    assert source is None and not scan.point_time_offsets_s.any() and scan.stamp_s == STAMP_NS * 1e-9
    assert C.no_point_time_notice("/x", msg) == (
        "[no_point_time] PointCloud2 on /x has no per-point time field (fields: x, y, z, intensity): deskewing is off "
        "(name the field in ros.inputs.lidar.time_field, or set it to none to say so)")


# ----------------------------------------------------------------------------- rejections


def test_a_configured_time_field_that_is_absent_rejects_every_frame():
    xyz, rel = _frame()
    msg = cloud({**xyz_columns(xyz), "t": (M.UINT32, np.round(rel * 1e9))})
    e = rejects(C.pointcloud2_to_scan, msg, time_field="time", name="missing_field", field="PointCloud2.fields")
    assert "'time'" in str(e) and "'t'" in str(e)


@pytest.mark.parametrize("name,dtype", [("t", M.FLOAT32), ("time", M.UINT32), ("timestamp", M.FLOAT32),
                                        ("offset_time", M.FLOAT64)])
def test_a_known_time_name_of_an_unknown_type_is_ambiguous(name, dtype):
    xyz, rel = _frame()
    msg = cloud({**xyz_columns(xyz), name: (dtype, rel)})
    e = rejects(C.pointcloud2_to_scan, msg, name="ambiguous_time", field=f"fields[{name!r}]")
    assert "time_field" in str(e)
    C.pointcloud2_to_scan(msg, time_field="none")       # says what to do: name it, or none


def test_timestamp_near_the_stamp_both_as_ns_and_as_s_is_ambiguous():
    """A header stamp under a second (a simulator's clock from 0): 0.55 s read as ns is 0 s, also
    within reach of a 0.5 s stamp."""
    xyz, rel = _frame()
    msg = cloud({**xyz_columns(xyz), "timestamp": (M.FLOAT64, 0.5 + rel)}, stamp_ns=500_000_000)
    rejects(C.pointcloud2_to_scan, msg, name="ambiguous_time", field="fields['timestamp']")
    scan = C.pointcloud2_to_scan(msg, time_field="timestamp", time_is_absolute=True)   # named: no guess
    np.testing.assert_allclose(point_times(scan), 0.5 + rel, atol=1e-6)


@pytest.mark.parametrize("what", ["span", "nan", "far", "neither_unit", "inf_big"])
def test_bad_times_are_named(what):
    xyz, rel = _frame()
    times, time_type, options = np.round(rel * 1e9), M.UINT32, {}
    name = "t"
    if what == "span":                      # 0.25 s in a 0.1 s frame: more than 2 frames
        times[-1] = 250_000_000
    elif what == "nan":
        name, time_type, times = "time", M.FLOAT32, rel.copy()
        times[3] = np.nan
    elif what == "far":                     # relative times 3 s after the stamp: a clock or unit mistake
        times = times + 3e9
    elif what == "neither_unit":
        name, time_type, times = "timestamp", M.FLOAT64, 1e5 + rel
    else:
        name, time_type, times = "time", M.FLOAT64, rel.copy()
        times[0] = 1e308
        options = dict(time_field="time", time_unit_s=1e3)
    msg = cloud({**xyz_columns(xyz), name: (time_type, times)})
    e = rejects(C.pointcloud2_to_scan, msg, name="bad_time", field=f"fields[{name!r}]", **options)
    assert "\n" not in str(e)


def test_the_span_limit_follows_the_nominal_frame_duration():
    xyz, _ = _frame(n=10)
    rel = np.linspace(0, 0.3, 10)
    msg = cloud({**xyz_columns(xyz), "time": (M.FLOAT64, rel)})
    rejects(C.pointcloud2_to_scan, msg, name="bad_time")
    scan = C.pointcloud2_to_scan(msg, nominal_frame_duration_s=0.2)     # a 5 Hz lidar: 0.3 s < 2 x 0.2 s
    assert scan.frame_duration_s == pytest.approx(0.3)


@settings(max_examples=150, deadline=None)
@given(fields=st.lists(st.builds(M.PointField, st.sampled_from(["x", "y", "z", "t", "time", "timestamp",
                                                                "offset_time", ""]),
                                 st.integers(0, 40), st.integers(0, 10), st.integers(0, 3)), max_size=7),
       width=st.integers(0, 6), height=st.integers(0, 3), point_step=st.integers(0, 48),
       stamp=st.sampled_from([0, 5 * 10**8, STAMP_NS]), big=st.booleans(), dense=st.booleans(),
       seed=st.integers(0, 1000), time_field=st.sampled_from(["auto", "none", "t", "timestamp"]))
def test_garbage_clouds_give_a_scan_or_a_named_rejection(fields, width, height, point_step, stamp, big, dense, seed,
                                                        time_field):
    data = np.random.default_rng(seed).integers(0, 256, width * height * point_step, dtype=np.uint8).tobytes()
    msg = M.PointCloud2(M.Header(M.Time(stamp // 10**9, stamp % 10**9), "f"), height, width, fields, big, point_step,
                        width * point_step, data, dense)
    try:
        C.pointcloud2_to_scan(msg, time_field=time_field)
    except M.RosMessageError as exc:
        assert "\n" not in str(exc)


# ----------------------------------------------------------------------------- the simulator's encoder


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 300), stamp_ns=st.integers(10**9, 2_100_000_000 * 10**9), seed=st.integers(0, 2**31))
def test_livox_encoder_round_trip(n, stamp_ns, seed):
    """What `dct hil serve` publishes decodes, off the wire, to the same points and point times."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-30, 30, (n, 3)).astype(np.float32)
    offs = np.sort(rng.uniform(0, 0.1, n)).astype(np.float32)
    msg = M.from_cdr(M.PointCloud2, M.to_cdr(C.livox_pointcloud2_msg(stamp_ns, "livox_frame", xyz, offs)))
    scan, source = C.pointcloud2_decode(msg)
    assert source == C.PointTime("timestamp", 1e-9, True, auto=True) and scan.frame_id == "livox_frame"
    np.testing.assert_array_equal(scan.points_m, xyz)
    # float64 ns of a 2036 time: 256 ns steps; float64 s of it: 240 ns
    want = offs.astype(np.float64) - offs.min()
    np.testing.assert_allclose(scan.point_time_offsets_s, want, atol=2e-6)
    assert scan.stamp_s == pytest.approx(stamp_ns * 1e-9 + float(offs.min()), abs=2e-6)


def test_livox_encoder_refuses_bad_shapes():
    with pytest.raises(ValueError, match="livox_pointcloud2_msg"):
        C.livox_pointcloud2_msg(STAMP_NS, "f", np.zeros((3, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="livox_pointcloud2_msg"):
        C.livox_pointcloud2_msg(STAMP_NS, "f", np.zeros((3, 3)), np.zeros(4))


# ----------------------------------------------------------------------------- the config and the receiver

PC2 = "sensor_msgs/msg/PointCloud2"


def test_lidar_config_time_field():
    from pydantic import ValidationError

    from runtime.io.ros.receiver import LidarTopic

    pc = {"topic": "/points", "type": PC2}
    assert LidarTopic.model_validate(pc).time_field == "auto"             # the default for PointCloud2
    assert LidarTopic.model_validate({**pc, "time_field": None}).time_field == "none"
    named = LidarTopic.model_validate({**pc, "time_field": "t", "time_unit_s": 1e-9, "time_is_absolute": False})
    assert (named.time_field, named.time_unit_s) == ("t", 1e-9)
    for bad, says in [({**pc, "time_unit_s": 1e-9}, "named time_field"),
                      ({**pc, "time_field": "none", "time_is_absolute": True}, "named time_field"),
                      ({**pc, "time_field": ""}, "not a field name"), ({**pc, "time_field": "t x"}, "not a field name"),
                      ({"topic": "/l", "type": "livox_ros_driver2/msg/CustomMsg", "time_field": "t"},
                       "PointCloud2 only"),
                      ({"topic": "/l", "type": "livox_ros_driver2/msg/CustomMsg", "time_unit_s": 1e-9},
                       "PointCloud2 only")]:
        with pytest.raises(ValidationError, match=says):
            LidarTopic.model_validate(bad)
    # the defaults written out (a dumped config) say nothing and load
    LidarTopic.model_validate({"topic": "/l", "type": "livox_ros_driver2/msg/CustomMsg", "time_field": "auto",
                               "time_unit_s": 1.0, "time_is_absolute": False})


def test_controller_config_with_a_pointcloud2_lidar(tmp_path):
    from calibration.errors import ConfigFileError
    from runtime.config import load_controller_config

    path = tmp_path / "c.yaml"
    path.write_text("ros:\n  inputs:\n    lidar: {topic: /livox/lidar, type: sensor_msgs/msg/PointCloud2}\n")
    lidar = load_controller_config(path).ros.inputs.lidar
    assert (lidar.type, lidar.time_field) == (PC2, "auto")
    path.write_text("ros:\n  inputs:\n    lidar: {topic: /p, type: sensor_msgs/msg/PointCloud2, time_field: t, "
                    "time_unit_s: 1.0e-9}\n")
    assert load_controller_config(path).ros.inputs.lidar.time_unit_s == 1e-9
    path.write_text("ros:\n  inputs:\n    lidar: {topic: /p, type: sensor_msgs/msg/PointCloud2, time_unit_s: 1.0e-9}\n")
    with pytest.raises(ConfigFileError, match="ros.inputs.lidar") as info:
        load_controller_config(path)
    assert "\n" not in str(info.value)


def _receiver(topic, domain_id: int):
    from runtime.io.ros.dds import CycloneTransport
    from runtime.io.ros.receiver import RosInputConfig, RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    inbox = SensorInbox()
    return RosSensorReceiver(RosInputConfig(domain_id=domain_id, lidar=topic), inbox, CycloneTransport(domain_id)), inbox


def test_receiver_says_once_that_the_clouds_have_no_time_field(caplog):
    from runtime.io.ros.receiver import LidarTopic

    topic = LidarTopic(topic="/pc2_no_time", type=PC2)
    rx, inbox = _receiver(topic, 160)
    handle = rx._handler("lidar", topic)
    assert rx.lidar_time_notice is None
    xyz, _ = _frame(n=20)
    with caplog.at_level("WARNING", logger="runtime.io.ros.receiver"):
        for k in range(3):
            msg = cloud({**xyz_columns(xyz + k), "intensity": (M.FLOAT32, 1.0)}, stamp_ns=STAMP_NS + k * 100_000_000)
            assert rx.process("lidar", PC2, M.to_cdr(msg), handle)
    assert inbox.accepted["lidar"] == 3                        # the scans are still used
    assert rx.lidar_time_notice.startswith("[no_point_time] PointCloud2 on /pc2_no_time has no per-point time field "
                                           "(fields: x, y, z, intensity): deskewing is off")
    said = [r.getMessage() for r in caplog.records if "no_point_time" in r.getMessage()]
    assert said == [rx.lidar_time_notice]                      # once, not per frame
    # a cloud with times, and time_field none, say nothing
    for tf, cols in (("auto", {"t": (M.UINT32, 5)}), ("none", {})):
        t2 = LidarTopic(topic="/pc2_quiet", type=PC2, time_field=tf)
        rx2, _ = _receiver(t2, 160)
        assert rx2.process("lidar", PC2, M.to_cdr(cloud({**xyz_columns(xyz), **cols})), rx2._handler("lidar", t2))
        assert rx2.lidar_time_notice is None


def test_receiver_rejects_every_frame_without_the_configured_field():
    from runtime.io.ros.receiver import LidarTopic

    topic = LidarTopic(topic="/pc2_missing", type=PC2, time_field="time")
    rx, inbox = _receiver(topic, 160)
    handle = rx._handler("lidar", topic)
    xyz, rel = _frame(n=20)
    for k in range(2):
        msg = cloud({**xyz_columns(xyz), "t": (M.UINT32, np.round(rel * 1e9))}, stamp_ns=STAMP_NS + k * 10**8)
        assert not rx.process("lidar", PC2, M.to_cdr(msg), handle)
    assert rx.error_counts == {"lidar.missing_field": 2} and inbox.accepted["lidar"] == 0
    assert "no time field 'time'" in rx.last_error
