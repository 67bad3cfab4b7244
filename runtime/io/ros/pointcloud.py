"""sensor_msgs/PointCloud2 <-> LidarScan: any driver's layout in, the Livox driver's layout out.

Inbound (`pointcloud2_to_scan`; `pointcloud2_decode` also says where the point times came from):
fields x, y, z (float32 or float64) at any offsets, any point_step, row padding (row_step) and
endianness, and each point's time from the field `time_field` names:

  "auto"      found from the message's fields, by the drivers' conventions (AUTO_TIME_FIELDS);
              none of them there: every point at the header stamp (deskewing off)
  "none"      every point at the header stamp
  a name      that field, times time_unit_s seconds, absolute or after the header stamp

  driver                              field        type     time
  livox_ros_driver2 (xfer_format 0)   timestamp    FLOAT64  absolute, ns
  Hesai, Robosense                    timestamp    FLOAT64  absolute, s
  Ouster                              t            UINT32   ns after the header stamp
  Livox CustomMsg -> PointCloud2      offset_time  UINT32   ns after the header stamp
  Velodyne                            time         FLOAT32  s relative to the header stamp

An absolute `timestamp` is read as ns or as s by which of the two lands near the header stamp
(2023 in ns is 1.7e18, in s 1.7e9: they differ by 1e9); one that lands near it both ways (a
stamp under a second or two) is `ambiguous_time`. A `t`, `time`, `timestamp` or `offset_time`
of another type is `ambiguous_time` too: name the field, its unit and whether it is absolute.

The times are checked (`bad_time`): finite, the earliest within MAX_STAMP_OFFSET_S of the header
stamp (farther is a clock or unit mistake), and spanning at most MAX_SPAN_FRAMES nominal frame
durations. They need not increase point by point (Livox's non-repetitive pattern and
multi-return clouds interleave). The scan starts at the earliest point (a driver that stamps the
frame's end gives negative relative times).

Non-finite points: an `is_dense=False` cloud declares that some points are invalid (no return);
those rows are dropped, and a cloud of only such points is `nothing_seen`. In an
`is_dense=True` cloud a NaN is a driver fault and LidarScan's `non_finite` rejection applies.

Outbound (`livox_pointcloud2_msg`): the livox_ros_driver2 xfer_format 0 layout (packed 26-byte
points: x, y, z, intensity float32, tag, line uint8, timestamp float64 absolute ns; the header
stamp is the first point's time), what `dct hil serve` publishes when the controller reads a
PointCloud2 lidar.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.common.sensor_data import MAX_LIDAR_POINTS, LidarScan, SensorDataError
from runtime.io.ros.messages import (
    FLOAT32, FLOAT64, INT8, INT16, INT32, UINT8, UINT16, UINT32, Header, PointCloud2, PointField, RosMessageError,
    Time,
)
from runtime.io.ros.validation import DEFAULT_FRAME_DURATION_S, fail, frame_id_of, rewrap, stamp_of

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TIME_FIELD_AUTO = "auto"
TIME_FIELD_NONE = "none"
#: The earliest point may be this far (s) from the header stamp; farther is a clock or unit mistake.
MAX_STAMP_OFFSET_S = 1.0
#: A frame's point times may span this many nominal frame durations.
MAX_SPAN_FRAMES = 2.0

# PointField.datatype -> numpy scalar type (little endian; swapped for is_bigendian)
_POINTFIELD_DTYPES = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4", UINT32: "u4",
                      FLOAT32: "f4", FLOAT64: "f8"}
_TYPE_NAMES = {INT8: "INT8", UINT8: "UINT8", INT16: "INT16", UINT16: "UINT16", INT32: "INT32", UINT32: "UINT32",
               FLOAT32: "FLOAT32", FLOAT64: "FLOAT64"}

#: time_field auto: (field, datatypes, unit in s (None: ns or s by magnitude), absolute, whose), in
#: the order they are looked for.
AUTO_TIME_FIELDS = (
    ("timestamp", (FLOAT64,), None, True, "livox_ros_driver2 (ns), Hesai and Robosense (s)"),
    ("t", (UINT32,), 1e-9, False, "Ouster"),
    ("offset_time", (UINT32,), 1e-9, False, "Livox CustomMsg converters"),
    ("time", (FLOAT32, FLOAT64), 1.0, False, "Velodyne"),
)


@dataclass(frozen=True)
class PointTime:
    """Where a cloud's per-point times came from: `field` in units of `unit_s`, absolute or after
    the header stamp; `auto`: found from the fields (time_field auto)."""

    field: str
    unit_s: float | None        # None only before an absolute `timestamp`'s unit is found
    absolute: bool
    auto: bool = False


# ----------------------------------------------------------------------------- layout


def _field_dtype(msg: PointCloud2) -> tuple[np.dtype, dict[str, PointField]]:
    """The numpy record type of one point (point_step bytes, fields at their offsets)."""
    t = POINTCLOUD2
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets, by_name = [], [], [], {}
    for f in msg.fields:
        if f.datatype not in _POINTFIELD_DTYPES:
            fail(t, f"fields[{f.name!r}].datatype", f"unknown datatype {f.datatype}", "bad_field")
        if f.name in by_name:
            fail(t, f"fields[{f.name!r}]", "field named twice", "bad_field")
        base = np.dtype(order + _POINTFIELD_DTYPES[f.datatype])
        count = max(int(f.count), 1)
        if f.offset + base.itemsize * count > msg.point_step:
            fail(t, f"fields[{f.name!r}].offset",
                 f"offset {f.offset} + {base.itemsize * count} bytes beyond point_step {msg.point_step}", "bad_field")
        by_name[f.name] = f
        names.append(f.name or f"_unnamed{len(names)}")
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(f.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step}), by_name


def _cloud_size(msg: PointCloud2) -> int:
    """The number of points of a cloud whose sizes (width, height, steps, data) agree."""
    t = POINTCLOUD2
    n = int(msg.width) * int(msg.height)
    if n == 0:
        fail(t, "width", f"empty cloud ({msg.width} x {msg.height})", "empty_scan")
    if n > MAX_LIDAR_POINTS:
        fail(t, "width", f"{n} points, more than {MAX_LIDAR_POINTS}", "too_many_points")
    if msg.point_step == 0:
        fail(t, "point_step", "0", "bad_size")
    if msg.row_step < msg.width * msg.point_step:
        fail(t, "row_step", f"{msg.row_step} < width {msg.width} x point_step {msg.point_step}", "bad_size")
    if len(msg.data) != msg.row_step * msg.height:
        fail(t, "data", f"{len(msg.data)} bytes, expected row_step {msg.row_step} x height {msg.height} "
             f"= {msg.row_step * msg.height}", "bad_size")
    return n


def _cloud_layout(msg: PointCloud2) -> tuple[np.dtype, dict[str, PointField]]:
    """The record type of one point and the fields by name, with float x, y, z."""
    t = POINTCLOUD2
    try:
        dtype, fields = _field_dtype(msg)
    except RosMessageError:
        raise
    except (ValueError, TypeError) as exc:    # numpy refuses the layout (a name it cannot take, ...)
        fail(t, "fields", f"no point layout: {exc}".splitlines()[0], "bad_field")
    for axis in ("x", "y", "z"):
        f = fields.get(axis)
        if f is None:
            fail(t, "fields", f"no {axis!r} field (has {sorted(fields)})", "missing_field")
        if f.datatype not in (FLOAT32, FLOAT64) or f.count != 1:
            fail(t, f"fields[{axis!r}]", f"datatype {f.datatype} count {f.count}, expected one FLOAT32/FLOAT64",
                 "bad_field")
    return dtype, fields


def _time_source(fields: dict[str, PointField], time_field: str | None, time_unit_s: float,
                 time_is_absolute: bool) -> PointTime | None:
    """The configured time field, or the one auto finds (unit None: by magnitude); None: no time."""
    t = POINTCLOUD2
    if time_field is None or time_field == TIME_FIELD_NONE:
        return None
    if time_field != TIME_FIELD_AUTO:
        f = fields.get(time_field)
        if f is None:
            fail(t, "fields", f"no time field {time_field!r} (has {sorted(fields)})", "missing_field")
        if f.count != 1:
            fail(t, f"fields[{time_field!r}]", f"count {f.count}, expected 1", "bad_field")
        return PointTime(time_field, float(time_unit_s), bool(time_is_absolute))
    for name, datatypes, unit, absolute, whose in AUTO_TIME_FIELDS:
        f = fields.get(name)
        if f is None:
            continue
        if f.datatype not in datatypes or f.count != 1:
            have = f"{_TYPE_NAMES.get(f.datatype, f.datatype)} x {f.count}"
            want = " or ".join(_TYPE_NAMES[d] for d in datatypes)
            fail(t, f"fields[{name!r}]", f"{have}, not the {want} of {whose}: set time_field, time_unit_s and "
                 "time_is_absolute", "ambiguous_time")
        return PointTime(name, unit, absolute, auto=True)   # unit None: found from the values
    return None


def _absolute_unit(name: str, times: np.ndarray, stamp: float, tolerance_s: float) -> float:
    """ns (1e-9) or s (1.0): the unit that puts the times near the header stamp."""
    t = POINTCLOUD2
    finite = times[np.isfinite(times)]
    if not len(finite):
        fail(t, f"fields[{name!r}]", "no finite point time", "bad_time")
    v = float(np.median(finite))
    fits = [u for u in (1e-9, 1.0) if abs(v * u - stamp) <= tolerance_s]
    if len(fits) == 2:
        fail(t, f"fields[{name!r}]", f"median {v:.9g} is within {tolerance_s:g} s of the header stamp {stamp:.3f} s "
             "both as ns and as s: set time_field and time_unit_s", "ambiguous_time")
    if not fits:
        fail(t, f"fields[{name!r}]", f"median {v:.9g} is neither ns nor s within {tolerance_s:g} s of the header "
             f"stamp {stamp:.3f} s", "bad_time")
    return fits[0]


# ----------------------------------------------------------------------------- inbound


def _relative_times(rec: np.ndarray, source: PointTime, stamp: float, nominal_s: float) -> tuple[np.ndarray, PointTime]:
    """Each point's time after the header stamp (s), and the source with its unit settled."""
    tt = rec[source.field].astype(np.float64)
    unit = source.unit_s
    if unit is None:
        unit = _absolute_unit(source.field, tt, stamp, MAX_STAMP_OFFSET_S + MAX_SPAN_FRAMES * nominal_s)
        source = PointTime(source.field, unit, source.absolute, source.auto)
    with np.errstate(over="ignore", invalid="ignore"):
        rel = (tt - stamp / unit) * unit if source.absolute else tt * unit
    return rel, source


def _check_times(rel: np.ndarray, source: PointTime, nominal_s: float) -> None:
    t, where = POINTCLOUD2, f"fields[{source.field!r}]"
    if not np.isfinite(rel).all():
        fail(t, where, f"{int((~np.isfinite(rel)).sum())} non-finite point time(s)", "bad_time")
    t0, t1 = float(rel.min()), float(rel.max())
    if abs(t0) > MAX_STAMP_OFFSET_S:
        fail(t, where, f"the first point is {t0:+.3f} s from the header stamp (at most {MAX_STAMP_OFFSET_S:g} s; "
             f"unit {source.unit_s:g} s, {'absolute' if source.absolute else 'relative'})", "bad_time")
    if t1 - t0 > MAX_SPAN_FRAMES * nominal_s:
        fail(t, where, f"point times span {t1 - t0:.4f} s, more than {MAX_SPAN_FRAMES:g} x the nominal frame "
             f"duration {nominal_s:g} s", "bad_time")


def pointcloud2_decode(msg: PointCloud2, *, time_field: str | None = TIME_FIELD_AUTO, time_unit_s: float = 1.0,
                       time_is_absolute: bool = False, nominal_frame_duration_s: float = DEFAULT_FRAME_DURATION_S,
                       default_frame_id: str = "lidar") -> tuple[LidarScan, PointTime | None]:
    """A PointCloud2 as a LidarScan (module docstring), and where its point times came from (None:
    every point at the header stamp). time_field None is "none"."""
    t = POINTCLOUD2
    stamp = stamp_of(t, msg.header)
    _cloud_size(msg)
    dtype, fields = _cloud_layout(msg)
    source = _time_source(fields, time_field, time_unit_s, time_is_absolute)
    buf = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    rec = np.ascontiguousarray(buf).view(dtype).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    if not msg.is_dense:
        keep = np.isfinite(xyz).all(axis=1)
        xyz, rec = xyz[keep], rec[keep]
    nominal = float(nominal_frame_duration_s)
    rel = np.zeros(len(xyz))
    if source is not None and len(xyz):
        rel, source = _relative_times(rec, source, stamp, nominal)
        _check_times(rel, source, nominal)
    t0 = float(rel.min()) if len(rel) else 0.0
    rel = rel - t0
    span = float(rel.max()) if len(rel) else 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        pts32 = xyz.astype(np.float32)
    try:
        scan = LidarScan(stamp_s=stamp + t0, points_m=pts32.reshape(-1, 3), point_time_offsets_s=rel.astype(np.float32),
                         frame_duration_s=max(nominal, span), frame_id=frame_id_of(t, msg.header, default_frame_id),
                         nothing_seen=len(xyz) == 0)
    except SensorDataError as exc:
        rewrap(t, "data", exc)
    return scan, source


def pointcloud2_to_scan(msg: PointCloud2, *, time_field: str | None = TIME_FIELD_AUTO, time_unit_s: float = 1.0,
                        time_is_absolute: bool = False, nominal_frame_duration_s: float = DEFAULT_FRAME_DURATION_S,
                        default_frame_id: str = "lidar") -> LidarScan:
    """A PointCloud2 as a LidarScan (module docstring); pointcloud2_decode without the time source."""
    return pointcloud2_decode(msg, time_field=time_field, time_unit_s=time_unit_s, time_is_absolute=time_is_absolute,
                              nominal_frame_duration_s=nominal_frame_duration_s, default_frame_id=default_frame_id)[0]


def no_point_time_notice(topic: str, msg: PointCloud2) -> str:
    """What to say once when time_field auto finds no per-point time in a topic's clouds."""
    names = ", ".join(f.name for f in msg.fields) or "none"
    return (f"[no_point_time] PointCloud2 on {topic} has no per-point time field (fields: {names}): deskewing is "
            "off (name the field in ros.inputs.lidar.time_field, or set it to none to say so)")


# ----------------------------------------------------------------------------- outbound

#: One point of livox_ros_driver2's PointCloud2 (xfer_format 0): packed, 26 bytes.
LIVOX_POINT_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
                              "formats": ["<f4", "<f4", "<f4", "<f4", "u1", "u1", "<f8"],
                              "offsets": [0, 4, 8, 12, 16, 17, 18], "itemsize": 26})
LIVOX_POINT_FIELDS = (PointField("x", 0, FLOAT32, 1), PointField("y", 4, FLOAT32, 1), PointField("z", 8, FLOAT32, 1),
                      PointField("intensity", 12, FLOAT32, 1), PointField("tag", 16, UINT8, 1),
                      PointField("line", 17, UINT8, 1), PointField("timestamp", 18, FLOAT64, 1))


def livox_pointcloud2_msg(timebase_ns: int, frame_id: str, points_m: np.ndarray, offsets_s: np.ndarray, *,
                          intensity: float = 100.0) -> PointCloud2:
    """A frame as livox_ros_driver2 publishes it in a PointCloud2 (xfer_format 0).

    timebase_ns: the first point's time (the header stamp, exactly); point i's `timestamp` is
    timebase_ns + offsets_s[i] in ns, as a float64 (as the driver writes it: 256 ns steps in 2023).
    """
    pts = np.asarray(points_m)
    offs = np.asarray(offsets_s, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or offs.shape != (len(pts),):
        raise ValueError(f"livox_pointcloud2_msg: points must be (N, 3) and offsets (N,), got {pts.shape} and "
                         f"{offs.shape}")
    timebase_ns = int(timebase_ns)
    if timebase_ns < 0:
        raise ValueError(f"livox_pointcloud2_msg: timebase_ns {timebase_ns} is negative")
    rec = np.zeros(len(pts), dtype=LIVOX_POINT_DTYPE)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["intensity"] = intensity
    rec["timestamp"] = (np.int64(timebase_ns) + np.round(offs * 1e9).astype(np.int64)).astype(np.float64)
    n = len(rec)
    return PointCloud2(
        header=Header(Time(timebase_ns // 1_000_000_000, timebase_ns % 1_000_000_000), frame_id), height=1, width=n,
        fields=list(LIVOX_POINT_FIELDS), is_bigendian=False, point_step=LIVOX_POINT_DTYPE.itemsize,
        row_step=LIVOX_POINT_DTYPE.itemsize * n, data=rec.tobytes(), is_dense=True)
