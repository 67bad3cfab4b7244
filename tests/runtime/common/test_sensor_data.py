"""Sensor data types: validation where data enters, named errors, ownership of buffers."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from runtime.common.sensor_data import (
    MAX_ACCEL_MPS2,
    MAX_GYRO_RADPS,
    MAX_LIDAR_POINTS,
    CameraImage,
    DtypeError,
    EmptyScanError,
    ImuSample,
    LidarScan,
    NonFiniteError,
    RangeError,
    SensorDataError,
    SensorStampChecker,
    ShapeError,
    StampError,
)

K640 = np.array([[337.2, 0.0, 319.5], [0.0, 337.2, 239.5], [0.0, 0.0, 1.0]])


def _scan(n: int = 100, **kw) -> LidarScan:
    rng = np.random.default_rng(0)
    args = dict(stamp_s=1.0, points_m=rng.uniform(-5, 5, (n, 3)).astype(np.float32),
                point_time_offsets_s=np.linspace(0, 0.099, n, dtype=np.float32), frame_duration_s=0.1)
    args.update(kw)
    return LidarScan(**args)


# ----------------------------------------------------------------------------- lidar


def test_valid_scan_is_read_only_and_keeps_values():
    pts = np.arange(30, dtype=np.float32).reshape(10, 3)
    offs = np.linspace(0, 0.05, 10, dtype=np.float32)
    scan = LidarScan(2.5, pts, offs, 0.1, "lidar")
    assert scan.num_points == 10
    np.testing.assert_array_equal(scan.points_m, pts)
    assert not scan.points_m.flags.writeable
    np.testing.assert_allclose(scan.point_stamps_s(), 2.5 + offs.astype(np.float64))


def test_scan_does_not_alias_a_writeable_producer_buffer():
    pts = np.ones((5, 3), dtype=np.float32)
    offs = np.zeros(5, dtype=np.float32)
    scan = LidarScan(0.0, pts, offs, 0.1)
    pts[:] = 7.0  # the producer reuses its buffer
    assert np.all(scan.points_m == 1.0)


def test_scan_is_copy_free_for_a_handed_over_read_only_array():
    pts = np.ones((5, 3), dtype=np.float32)
    pts.flags.writeable = False
    scan = LidarScan(0.0, pts, np.zeros(5, np.float32), 0.1)
    assert np.shares_memory(scan.points_m, pts)


def test_read_only_view_of_writeable_buffer_is_copied():
    buf = np.ones((5, 3), dtype=np.float32)
    view = buf[:]
    view.flags.writeable = False
    scan = LidarScan(0.0, view, np.zeros(5, np.float32), 0.1)
    buf[:] = 3.0
    assert np.all(scan.points_m == 1.0)


def test_float64_points_are_converted_to_float32():
    scan = LidarScan(0.0, np.ones((4, 3)), np.zeros(4), 0.1)
    assert scan.points_m.dtype == np.float32 and scan.point_time_offsets_s.dtype == np.float32


def test_nan_point_is_named_error():
    pts = np.ones((6, 3), dtype=np.float32)
    pts[4, 2] = np.nan
    with pytest.raises(NonFiniteError) as e:
        _scan(points_m=pts, point_time_offsets_s=np.zeros(6, np.float32))
    assert e.value.name == "non_finite" and e.value.field_name == "points_m"
    assert "(4, 2)" in str(e.value)


def test_overflow_to_float32_is_non_finite():
    pts = np.full((2, 3), 1e300)
    with pytest.raises(NonFiniteError):
        LidarScan(0.0, pts, np.zeros(2), 0.1)


@pytest.mark.parametrize("shape", [(10,), (10, 2), (10, 4), (2, 5, 3)])
def test_wrong_point_shape(shape):
    with pytest.raises(ShapeError) as e:
        LidarScan(0.0, np.zeros(shape, np.float32), np.zeros(10, np.float32), 0.1)
    assert e.value.name == "bad_shape"


def test_time_offsets_must_match_points():
    with pytest.raises(ShapeError):
        LidarScan(0.0, np.zeros((10, 3), np.float32), np.zeros(9, np.float32), 0.1)


@pytest.mark.parametrize("bad", [-0.001, 0.1001, 0.5])
def test_time_offsets_outside_frame(bad):
    offs = np.zeros(3, np.float32)
    offs[1] = bad
    with pytest.raises(RangeError) as e:
        LidarScan(0.0, np.zeros((3, 3), np.float32), offs, 0.1)
    assert e.value.field_name == "point_time_offsets_s"


def test_integer_points_are_rejected():
    with pytest.raises(DtypeError):
        LidarScan(0.0, np.zeros((3, 3), np.int32), np.zeros(3, np.float32), 0.1)


def test_empty_scan_needs_the_sensor_to_say_so():
    empty_p, empty_t = np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    with pytest.raises(EmptyScanError) as e:
        LidarScan(0.0, empty_p, empty_t, 0.1)
    assert e.value.name == "empty_scan"
    assert LidarScan(0.0, empty_p, empty_t, 0.1, nothing_seen=True).num_points == 0
    with pytest.raises(SensorDataError) as e2:
        _scan(nothing_seen=True)
    assert e2.value.name == "inconsistent_empty_flag"


def test_too_many_points():
    n = MAX_LIDAR_POINTS + 1
    with pytest.raises(RangeError) as e:
        LidarScan(0.0, np.zeros((n, 3), np.float32), np.zeros(n, np.float32), 0.1)
    assert e.value.name == "too_many_points"


@pytest.mark.parametrize("d", [0.0, -0.1, 2.0, math.nan, math.inf])
def test_bad_frame_duration(d):
    with pytest.raises(RangeError):
        _scan(frame_duration_s=d)


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -1.0, "abc"])
def test_bad_scan_stamp(stamp):
    with pytest.raises(StampError):
        _scan(stamp_s=stamp)


def test_far_point_out_of_range():
    pts = np.zeros((2, 3), np.float32)
    pts[0, 0] = 5000.0
    with pytest.raises(RangeError):
        LidarScan(0.0, pts, np.zeros(2, np.float32), 0.1)


def test_frame_id_must_be_named():
    with pytest.raises(SensorDataError) as e:
        _scan(frame_id="")
    assert e.value.name == "bad_frame_id"


def test_scan_is_frozen():
    scan = _scan()
    with pytest.raises(AttributeError):
        scan.stamp_s = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        scan.points_m[0, 0] = 1.0


_finite32 = st.floats(-500, 500, allow_nan=False, allow_infinity=False, width=32)


@settings(max_examples=60, deadline=None)
@given(pts=hnp.arrays(np.float32, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=40)
                      .map(lambda s: (s[0], 3)), elements=_finite32),
       frac=st.floats(0.0, 1.0))
def test_property_finite_scans_are_accepted(pts, frac):
    n = pts.shape[0]
    offs = np.full(n, frac * 0.1, dtype=np.float32)
    scan = LidarScan(0.0, pts, offs, 0.1)
    np.testing.assert_array_equal(scan.points_m, pts)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 40), i=st.integers(0, 10_000), j=st.integers(0, 2),
       bad=st.sampled_from([np.nan, np.inf, -np.inf]))
def test_property_any_non_finite_coordinate_is_rejected(n, i, j, bad):
    pts = np.zeros((n, 3), np.float32)
    pts[i % n, j] = bad
    with pytest.raises(NonFiniteError):
        LidarScan(0.0, pts, np.zeros(n, np.float32), 0.1)


@settings(max_examples=60, deadline=None)
@given(arr=hnp.arrays(np.float32, hnp.array_shapes(min_dims=1, max_dims=3, max_side=6),
                      elements=_finite32))
def test_property_points_shape_is_n_by_3_or_error(arr):
    n = arr.shape[0]
    ok = arr.ndim == 2 and arr.shape[1] == 3 and n > 0
    if ok:
        LidarScan(0.0, arr, np.zeros(n, np.float32), 0.1)
    else:
        with pytest.raises(SensorDataError):
            LidarScan(0.0, arr, np.zeros(n, np.float32), 0.1)


# ----------------------------------------------------------------------------- camera


def test_valid_image_and_segmentation():
    px = np.zeros((480, 640, 3), np.uint8)
    seg = np.full((480, 640), -1, np.int32)
    img = CameraImage(0.5, px, K640, np.zeros(5), "camera", segmentation=seg)
    assert (img.width, img.height) == (640, 480)
    assert img.K.dtype == np.float64 and not img.pixels.flags.writeable


@pytest.mark.parametrize("shape", [(480, 640), (480, 640, 4), (480, 640, 1), (0, 640, 3)])
def test_bad_image_shape(shape):
    with pytest.raises(SensorDataError):
        CameraImage(0.0, np.zeros(shape, np.uint8), K640)


def test_float_pixels_rejected():
    with pytest.raises(DtypeError):
        CameraImage(0.0, np.zeros((4, 4, 3), np.float32), K640)


@pytest.mark.parametrize("mutate", [
    lambda K: K.__setitem__((0, 0), -1.0),
    lambda K: K.__setitem__((1, 1), np.nan),
    lambda K: K.__setitem__((2, 2), 2.0),
    lambda K: K.__setitem__((1, 0), 0.5),
    lambda K: K.__setitem__((0, 2), 5000.0),
])
def test_bad_intrinsics(mutate):
    K = K640.copy()
    mutate(K)
    with pytest.raises(SensorDataError):
        CameraImage(0.0, np.zeros((480, 640, 3), np.uint8), K)


def test_intrinsics_shape():
    with pytest.raises(ShapeError):
        CameraImage(0.0, np.zeros((480, 640, 3), np.uint8), np.eye(4))


@pytest.mark.parametrize("n", [1, 3, 6])
def test_distortion_length(n):
    with pytest.raises(ShapeError):
        CameraImage(0.0, np.zeros((480, 640, 3), np.uint8), K640, np.zeros(n))


def test_segmentation_must_match_image():
    with pytest.raises(ShapeError):
        CameraImage(0.0, np.zeros((480, 640, 3), np.uint8), K640, segmentation=np.zeros((480, 641), np.int32))
    k_small = np.array([[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]])
    CameraImage(0.0, np.zeros((2, 2, 3), np.uint8), k_small, segmentation=np.array([[0, -1], [1, 1]], np.int32))
    with pytest.raises(RangeError) as e:
        CameraImage(0.0, np.zeros((2, 2, 3), np.uint8), k_small, segmentation=np.array([[0, -2], [1, 1]], np.int32))
    assert e.value.field_name == "segmentation"
    with pytest.raises(RangeError) as e:  # would wrap around in int32
        CameraImage(0.0, np.zeros((1, 2, 3), np.uint8), np.array([[1.0, 0, 1], [0, 1, 0.5], [0, 0, 1]]),
                    segmentation=np.array([[0, 2**40]], np.int64))
    assert e.value.field_name == "segmentation"


# ----------------------------------------------------------------------------- IMU


def test_imu_sample_ok_and_limits():
    s = ImuSample(0.01, [0.0, 0.0, 0.1], [0.0, 0.0, 9.81])
    assert s.accel_mps2.shape == (3,) and s.accel_mps2.dtype == np.float64
    with pytest.raises(RangeError):
        ImuSample(0.01, [0.0, 0.0, 0.0], [0.0, 0.0, MAX_ACCEL_MPS2 * 1.01])
    with pytest.raises(ShapeError):
        ImuSample(0.01, [0.0, 0.0], [0.0, 0.0, 9.81])
    with pytest.raises(NonFiniteError):
        ImuSample(0.01, [0.0, np.nan, 0.0], [0.0, 0.0, 9.81])
    with pytest.raises(DtypeError):
        ImuSample(0.01, np.array([True, False, True]), [0.0, 0.0, 9.81])


def test_imu_saturated_flag_limits_included():
    """A clipping sensor reports exactly its range, flagged; beyond the range it is out_of_range
    with or without the flag."""
    at_limit = ImuSample(0.01, [MAX_GYRO_RADPS, -MAX_GYRO_RADPS, 0.0], [0.0, -MAX_ACCEL_MPS2, MAX_ACCEL_MPS2],
                         saturated=True)
    assert at_limit.saturated is True
    assert ImuSample(0.01, [0.0, 0.0, MAX_GYRO_RADPS], [0.0, 0.0, MAX_ACCEL_MPS2]).saturated is False
    assert ImuSample(0.01, [0.0, 0.0, 0.1], [0.0, 0.0, 9.81], saturated=np.bool_(True)).saturated is True
    beyond = np.nextafter(MAX_GYRO_RADPS, np.inf)
    for flag in (False, True):
        with pytest.raises(RangeError) as err:
            ImuSample(0.01, [beyond, 0.0, 0.0], [0.0, 0.0, 9.81], saturated=flag)
        assert err.value.name == "out_of_range" and err.value.field_name == "gyro_radps"
        with pytest.raises(RangeError, match="accel_mps2"):
            ImuSample(0.01, [0.0, 0.0, 0.0], [0.0, 0.0, -np.nextafter(MAX_ACCEL_MPS2, np.inf)], saturated=flag)
    with pytest.raises(SensorDataError) as err:
        ImuSample(0.01, [0.0, 0.0, 0.1], [0.0, 0.0, 9.81], saturated=1)
    assert err.value.name == "bad_flag" and err.value.field_name == "saturated"


@settings(max_examples=80, deadline=None)
@given(g=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3),
       a=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=3, max_size=3))
def test_property_imu_accepts_exactly_the_sane_samples(g, a):
    sane = all(math.isfinite(x) and abs(x) <= 34.9 for x in g) and all(
        math.isfinite(x) and abs(x) <= MAX_ACCEL_MPS2 for x in a)
    insane = any(not math.isfinite(x) or abs(x) > 35.0 for x in g) or any(
        not math.isfinite(x) or abs(x) > MAX_ACCEL_MPS2 for x in a)
    if sane:
        ImuSample(0.0, g, a)
    elif insane:
        with pytest.raises(SensorDataError):
            ImuSample(0.0, g, a)


# ----------------------------------------------------------------------------- stamps


def test_stamp_checker_monotonic_per_stream():
    c = SensorStampChecker()
    c.check("lidar", 1.0)
    c.check("imu", 0.5)  # other stream: independent
    with pytest.raises(StampError) as e:
        c.check("lidar", 1.0)
    assert e.value.name == "non_monotonic_stamp"
    with pytest.raises(StampError):
        c.check("lidar", 0.9)
    assert c.last_stamp("lidar") == 1.0  # rejected stamps do not move the state
    c.check("lidar", 1.1)
    c.reset("lidar")
    c.check("lidar", 0.2)


def test_stamp_checker_stale_and_future():
    c = SensorStampChecker(max_age_s={"lidar": 0.25}, future_tolerance_s=0.01)
    with pytest.raises(StampError) as e:
        c.check("lidar", 1.0, now_s=1.3)
    assert e.value.name == "stale_stamp"
    with pytest.raises(StampError) as e:
        c.check("lidar", 1.5, now_s=1.3)
    assert e.value.name == "future_stamp"
    c.check("lidar", 1.2, now_s=1.3)
    c.check("camera", 0.0, now_s=100.0)  # no age limit configured for this stream


def test_stamp_checker_rejects_bad_config_and_stamps():
    with pytest.raises(ValueError):
        SensorStampChecker(max_age_s=-1.0)
    c = SensorStampChecker(0.1)
    with pytest.raises(StampError) as e:
        c.check("x", float("nan"))
    assert e.value.name == "non_finite_stamp"


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0.0, 1e6, allow_nan=False), min_size=1, max_size=30))
def test_property_checker_accepts_exactly_the_strictly_increasing_prefix_maxima(stamps):
    c = SensorStampChecker()
    last = None
    for s in stamps:
        if last is None or s > last:
            assert c.check("s", s) == s
            last = s
        else:
            with pytest.raises(StampError):
                c.check("s", s)
    assert c.last_stamp("s") == last
