"""sensor_msgs/CameraInfo -> the camera driver's intrinsics (what the calibration check compares):
binning and region of interest applied as image_geometry does, an uncalibrated driver named,
anything else a one-line RosMessageError."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from runtime.common.sensor_data import SensorDataError
from runtime.io.ros import convert, messages as M
from runtime.io.ros.messages import RosMessageError
from runtime.io.ros.receiver import decode_cdr
from runtime.io.sensor_inbox import SensorInbox

K = [336.0, 0.0, 319.5, 0.0, 337.0, 239.5, 0.0, 0.0, 1.0]


def info(**changes) -> M.CameraInfo:
    fields = dict(header=M.Header(M.Time(12, 500_000_000), "camera_color_optical_frame"), height=480, width=640,
                  distortion_model="plumb_bob", d=[-0.05, 0.01, 0.0, 0.0, 0.0], k=list(K))
    fields.update(changes)
    return M.CameraInfo(**fields)


def test_a_driver_camera_info_as_intrinsics():
    out = convert.camera_info_to_intrinsics(decode_cdr(convert.CAMERA_INFO, M.to_cdr(info())))
    assert (out.width_px, out.height_px, out.stamp_s, out.frame_id) == (640, 480, 12.5, "camera_color_optical_frame")
    np.testing.assert_array_equal(out.K, np.reshape(K, (3, 3)))
    np.testing.assert_array_equal(out.distortion, [-0.05, 0.01, 0.0, 0.0, 0.0])
    assert out.distortion_model == "plumb_bob"
    inbox = SensorInbox()
    assert inbox.put_camera_info(out) and inbox.take().camera_info is out and inbox.take().camera_info is None


def test_binning_and_region_of_interest_are_applied():
    out = convert.camera_info_to_intrinsics(info(binning_x=2, binning_y=2, roi=M.RegionOfInterest(40, 20, 400, 600)))
    assert (out.width_px, out.height_px) == (300, 200)
    np.testing.assert_allclose(out.K, [[168.0, 0.0, 139.75], [0.0, 168.5, 109.75], [0.0, 0.0, 1.0]])


def test_a_driver_without_a_calibration_is_named():
    with pytest.raises(RosMessageError, match=r"^\[uncalibrated\] sensor_msgs/msg/CameraInfo\.k: all zero"):
        convert.camera_info_to_intrinsics(info(k=[0.0] * 9))


@pytest.mark.parametrize("changes, field", [
    (dict(k=[336.0, 0.0, 319.5, 0.0, -1.0, 239.5, 0.0, 0.0, 1.0]), "sensor_msgs/msg/CameraInfo.k"),
    (dict(k=[float("nan")] + K[1:]), "sensor_msgs/msg/CameraInfo.k"),
    (dict(width=0), "sensor_msgs/msg/CameraInfo.width"),
    (dict(d=[float("inf")]), "sensor_msgs/msg/CameraInfo.d"),
    (dict(distortion_model="kannala"), "sensor_msgs/msg/CameraInfo.distortion_model"),
])
def test_a_bad_field_is_one_line_naming_it(changes, field):
    with pytest.raises(RosMessageError) as err:
        convert.camera_info_to_intrinsics(info(**changes))
    assert err.value.field_name == field and "\n" not in str(err.value)


_f = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=150, deadline=None)
@given(k=st.lists(_f, min_size=9, max_size=9), d=st.lists(_f, max_size=16), w=st.integers(0, 2**32 - 1),
       h=st.integers(0, 2**32 - 1), bx=st.integers(0, 2**32 - 1), model=st.sampled_from(
           ["plumb_bob", "rational_polynomial", "equidistant", "", "x"]),
       roi=st.tuples(*[st.integers(0, 2**32 - 1)] * 4))
def test_any_camera_info_gives_intrinsics_or_a_named_rejection(k, d, w, h, bx, model, roi):
    msg = info(k=k, d=d, width=w, height=h, binning_x=bx, distortion_model=model, roi=M.RegionOfInterest(*roi))
    try:
        out = convert.camera_info_to_intrinsics(decode_cdr(convert.CAMERA_INFO, M.to_cdr(msg)))
    except RosMessageError as exc:
        assert str(exc).startswith("[") and exc.field_name.startswith("sensor_msgs/msg/CameraInfo.")
        return
    out.validate()
    assert np.isfinite(out.K).all() and out.K[0, 0] > 0 and out.K[1, 1] > 0


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=400))
def test_any_bytes_decode_or_are_named(data):
    try:
        convert.camera_info_to_intrinsics(decode_cdr(convert.CAMERA_INFO, data))
    except SensorDataError as exc:
        assert "\n" not in str(exc)
