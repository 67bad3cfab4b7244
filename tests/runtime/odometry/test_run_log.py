"""Recorded odometry runs (.npz): round trip, atomic and non-clobbering writes, and a loader that
refuses every malformed file with its own one-line error, whatever the bytes."""
from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from calibration.outputs import OutputPathError
from runtime.odometry.run_log import FORMAT_VERSION, OdometryRunLog, RunLogError, load_run_log


def _run(n: int = 20, **over) -> OdometryRunLog:
    rng = np.random.default_rng(1)
    fields = dict(
        t_s=5.0 + 0.05 * np.arange(n),
        left_wheel_m=np.cumsum(rng.uniform(0, 0.01, n)),
        right_wheel_m=np.cumsum(rng.uniform(0, 0.01, n)),
        gyro_z_radps=np.where(np.arange(n) % 7 == 3, np.nan, rng.normal(0, 0.1, n)),
        ref_pose=rng.normal(0, 1, (n, 3)),
        reference="ground_truth", robot="limo", source="scenario case1 seed 3",
    )
    fields.update(over)
    return OdometryRunLog(**fields)


def _members(run: OdometryRunLog) -> dict:
    out = {k: getattr(run, k) for k in ("t_s", "left_wheel_m", "right_wheel_m", "gyro_z_radps", "ref_pose")}
    out.update(reference=np.array(run.reference), robot=np.array(run.robot), source=np.array(run.source),
               format_version=np.array(FORMAT_VERSION))
    return out


def _write_npz(path, **members) -> None:
    with open(path, "wb") as f:
        np.savez(f, **members)


@pytest.fixture(scope="module")
def valid_bytes(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("run") / "run.npz"
    _run(50).save(path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("scratch")


# ---------------------------------------------------------------------------- round trip and writes
def test_round_trip_keeps_every_value_and_nan_gyro(tmp_path):
    run = _run()
    path = run.save(tmp_path / "run.npz")
    back = load_run_log(path)
    for name in ("t_s", "left_wheel_m", "right_wheel_m", "gyro_z_radps", "ref_pose"):
        np.testing.assert_array_equal(getattr(back, name), getattr(run, name))
        assert getattr(back, name).dtype == np.float64
    assert (back.reference, back.robot, back.source) == ("ground_truth", "limo", "scenario case1 seed 3")
    assert np.isnan(back.gyro_z_radps).sum() == 3 and len(back) == 20
    assert OdometryRunLog.load(path).source == run.source


def test_arrays_are_float64_copies_that_cannot_change(tmp_path):
    t = np.arange(5, dtype=np.float32)
    run = _run(5, t_s=t)
    t[0] = 99.0
    assert run.t_s[0] == 0.0 and run.t_s.dtype == np.float64
    with pytest.raises(ValueError):
        run.t_s[1] = 3.0


def test_save_refuses_an_existing_file_unless_overwrite(tmp_path):
    path = tmp_path / "run.npz"
    _run(10).save(path)
    before = path.read_bytes()
    with pytest.raises(OutputPathError, match="already exists"):
        _run(12).save(path)
    assert path.read_bytes() == before
    _run(12).save(path, overwrite=True)
    assert len(load_run_log(path)) == 12
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.npz"]  # no temporary file left


def test_save_refuses_a_missing_folder(tmp_path):
    with pytest.raises(OutputPathError, match="does not exist"):
        _run().save(tmp_path / "nope" / "run.npz")


# ---------------------------------------------------------------------------- validation
@pytest.mark.parametrize("over, field, fragment", [
    ({"t_s": np.array([0.0, 0.1, 0.1, 0.2])}, "t_s", "strictly increasing"),
    ({"t_s": np.array([0.0, 0.2, 0.1, 0.3])}, "t_s", "tick 2"),
    ({"t_s": np.array([0.0])}, "t_s", "at least 2 ticks"),
    ({"t_s": np.zeros((4, 1))}, "t_s", "shape (N,)"),
    ({"t_s": np.arange(4)}, "t_s", "float32 or float64"),
    ({"left_wheel_m": np.array([0.0, np.nan, 0.0, 0.0])}, "left_wheel_m", "tick 1 is nan"),
    ({"right_wheel_m": np.zeros(3)}, "right_wheel_m", "N = 4"),
    ({"gyro_z_radps": np.array([0.0, np.inf, 0.0, 0.0])}, "gyro_z_radps", "finite or NaN"),
    ({"ref_pose": np.zeros((4, 2))}, "ref_pose", "(N, 3)"),
    ({"ref_pose": np.full((4, 3), np.nan)}, "ref_pose", "finite"),
    ({"ref_pose": np.zeros((4, 3), dtype=np.float16)}, "ref_pose", "float32 or float64"),
    ({"reference": "gps"}, "reference", "ground_truth, icp"),
    ({"robot": " "}, "robot", "empty"),
    ({"source": "x" * 1001}, "source", "longer than"),
])
def test_bad_fields_are_named(over, field, fragment):
    n = 4
    base = dict(t_s=np.arange(n, dtype=float), left_wheel_m=np.zeros(n), right_wheel_m=np.zeros(n),
                gyro_z_radps=np.zeros(n), ref_pose=np.zeros((n, 3)), reference="icp", robot="limo", source="")
    base.update(over)
    with pytest.raises(RunLogError) as exc:
        OdometryRunLog(**base)
    msg = str(exc.value)
    assert msg.startswith(f"odometry run: {field}: ") and fragment in msg and "\n" not in msg, msg


def test_float32_file_loads_as_float64(tmp_path):
    m = _members(_run(6))
    m["ref_pose"] = m["ref_pose"].astype(np.float32)
    _write_npz(tmp_path / "r.npz", **m)
    assert load_run_log(tmp_path / "r.npz").ref_pose.dtype == np.float64


@pytest.mark.parametrize("change, fragment", [
    (lambda m: m.pop("ref_pose"), "ref_pose: missing"),
    (lambda m: m.pop("format_version"), "format_version: missing"),
    (lambda m: m.update(format_version=np.array(2)), "format_version: must be the integer 1"),
    (lambda m: m.update(format_version=np.array("1")), "format_version"),
    (lambda m: m.update(extra=np.zeros(3)), "unknown member(s) 'extra'"),
    (lambda m: m.update({"a\nb": np.zeros(3)}), "unknown member(s) 'a\\nb'"),
    (lambda m: m.update(robot=np.array(["limo", "x"])), "robot: must be a text value"),
    (lambda m: m.update(reference=np.array(b"icp")), "reference: must be a text value"),
    (lambda m: m.update(reference=np.array("slam")), "reference: must be one of"),
    (lambda m: m.update(t_s=m["t_s"][::-1].copy()), "t_s: must be strictly increasing"),
    (lambda m: m.update(gyro_z_radps=m["gyro_z_radps"][:-1]), "gyro_z_radps: must have shape (N,)"),
])
def test_bad_files_are_named_with_file_and_member(tmp_path, change, fragment):
    m = _members(_run(6))
    change(m)
    path = tmp_path / "bad.npz"
    _write_npz(path, **m)
    with pytest.raises(RunLogError) as exc:
        load_run_log(path)
    msg = str(exc.value)
    assert msg.startswith(f"odometry run {path}: ") and fragment in msg and "\n" not in msg, msg


def test_pickled_members_are_refused_not_loaded(tmp_path):
    m = _members(_run(6))
    m["source"] = np.array([{"evil": 1}], dtype=object)  # stored as a pickle
    path = tmp_path / "pickled.npz"
    _write_npz(path, **m)
    with pytest.raises(RunLogError, match="cannot be read as an .npz run file.*allow_pickle"):
        load_run_log(path)


def test_not_a_run_file(tmp_path):
    with pytest.raises(RunLogError, match="no such file"):
        load_run_log(tmp_path / "missing.npz")
    with pytest.raises(RunLogError, match="is not a file"):
        load_run_log(tmp_path)
    np.save(tmp_path / "a.npy", np.zeros(3))
    with pytest.raises(RunLogError, match="single .npy array"):
        load_run_log(tmp_path / "a.npy")
    for name, data in (("empty.npz", b""), ("text.npz", b"t_s,left\n0.0,0.0\n")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(RunLogError, match=r"is not an .npz file \(no zip signature"):
            load_run_log(tmp_path / name)
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04" + bytes(40))
    with pytest.raises(RunLogError, match="cannot be read as an .npz run file"):
        load_run_log(tmp_path / "cut.npz")


# ---------------------------------------------------------------------------- any bytes
def _load_bytes(folder, data: bytes) -> OdometryRunLog:
    path = folder / "fuzz.npz"
    path.write_bytes(data)
    return load_run_log(path)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=2000))
def test_random_bytes_raise_only_run_log_error(scratch, data):
    with pytest.raises(RunLogError):
        _load_bytes(scratch, data)


@settings(max_examples=150, deadline=None)
@given(fraction=st.floats(0.0, 1.0, exclude_max=True))
def test_truncated_files_raise_only_run_log_error(scratch, valid_bytes, fraction):
    with pytest.raises(RunLogError):
        _load_bytes(scratch, valid_bytes[: int(fraction * len(valid_bytes))])


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_corrupted_bytes_load_or_raise_run_log_error(scratch, valid_bytes, data):
    corrupted = bytearray(valid_bytes)
    for _ in range(data.draw(st.integers(1, 8))):
        i = data.draw(st.integers(0, len(corrupted) - 1))
        corrupted[i] = data.draw(st.integers(0, 255))
    try:
        run = _load_bytes(scratch, bytes(corrupted))
    except RunLogError:
        return
    assert len(run) == 50  # a flip the format does not see (e.g. a zip timestamp) still loads a valid run


@settings(max_examples=100, deadline=None)
@given(name=st.sampled_from(["t_s", "left_wheel_m", "right_wheel_m", "gyro_z_radps", "ref_pose"]),
       shape=st.lists(st.integers(0, 7), min_size=0, max_size=3).map(tuple),
       dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_, np.complex128, np.uint8]))
def test_wrong_shapes_and_dtypes_name_the_member(scratch, name, shape, dtype):
    m = _members(_run(6))
    good = m[name]
    m[name] = np.ones(shape, dtype=dtype) if name != "t_s" else np.arange(int(np.prod(shape))).reshape(shape).astype(dtype)
    buf = io.BytesIO()
    np.savez(buf, **m)
    try:
        run = _load_bytes(scratch, buf.getvalue())
    except RunLogError as exc:
        msg = str(exc)
        assert "\n" not in msg
        if name != "t_s":  # t_s sets N: a wrong t_s may be reported by the first member that then mismatches
            assert f": {name}: " in msg, msg
        return
    # Only a replacement the format allows loads: the right shape and a float dtype.
    assert m[name].dtype.kind == "f" and getattr(run, name).shape == good.shape


def test_a_zip_member_that_is_not_an_array_is_refused(tmp_path, valid_bytes):
    path = tmp_path / "z.npz"
    path.write_bytes(valid_bytes)
    with zipfile.ZipFile(path, "a") as z:
        z.writestr("notes.txt", b"not an npy")  # numpy hands this out as bytes, not an array
    with pytest.raises(RunLogError, match=r"z.npz: notes.txt: is not a numpy array"):
        load_run_log(path)


_NAMES = ["format_version", "t_s", "left_wheel_m", "right_wheel_m", "gyro_z_radps", "ref_pose", "reference",
          "robot", "source", "other"]
_npy = hnp.arrays(dtype=st.sampled_from([np.float64, np.float32, np.int64, np.bool_, np.dtype("<U4"), np.dtype("S3"),
                                         np.dtype([("a", "<f8")])]),
                  shape=hnp.array_shapes(min_dims=0, max_dims=2, min_side=0, max_side=5))


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


@settings(max_examples=200, deadline=None)
@given(members=st.dictionaries(st.one_of(st.sampled_from(_NAMES),
                                         st.text(st.characters(exclude_categories=("Cs",), exclude_characters="\x00"),
                                                 max_size=8)),
                               st.one_of(st.binary(max_size=100), _npy.map(_npy_bytes)), max_size=len(_NAMES)),
       compression=st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
def test_zips_of_random_members_raise_only_run_log_error(scratch, members, compression):
    """Well-formed zips whose members are random bytes or arrays of any dtype and shape."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as z:
        for name, data in members.items():
            z.writestr(f"{name}.npy", data)
    try:
        run = _load_bytes(scratch, buf.getvalue())
    except RunLogError as exc:
        assert "\n" not in str(exc)
        return
    assert len(run) >= 2 and np.all(np.diff(run.t_s) > 0)  # a valid run by chance: it passed every check
