"""dct deploy bundle and its install.sh.

Fast tests build the bundle with a tiny fake wheelhouse (one pure-Python wheel named
dct-controller that provides a `dct` script and a `ros` extra, and a stand-in wheel for each
package of that extra) and run the real install.sh into a fresh venv: manifest, offline install,
refusal of a changed file, output-path rules, the unit's contents, the three ways ROS 2 comes
(--ros wheels, system with a stand-in setup script, none).
The slow test builds the real bundle (every pinned wheel, about 450 MB), installs it offline
into a fresh venv and runs the installed `dct preflight` against the emulated base on a
udp_multicast bus and sensor topics published by this process (`-m slow`)."""
from __future__ import annotations

import base64
import hashlib
import json
import os
import queue
import socket
import subprocess
import sys
import tarfile
import threading
import time
import zipfile
from importlib import metadata, resources
from pathlib import Path

import pytest
import yaml

from runtime.app.deploy import bundle as B
from runtime.app.deploy.sd_notify import SystemdNotifier
from tests.runtime.app.preflight.fakes import unique_domain, unique_port

LIMO = Path(str(resources.files("calibration") / "robots" / "limo.yaml"))
VERSION = metadata.version("dct-controller")


ROS_EXTRA = B.ros_extra_requirements()


def fake_wheel(folder: Path, name: str = "dct-controller", version: str = VERSION, ros_extra=ROS_EXTRA) -> Path:
    """A valid pure-Python wheel `name`-`version`; the project's (dct-controller) has a `dct` that
    prints its arguments and a `ros` extra naming `ros_extra` (name, version) as the real one does."""
    stem = name.replace("-", "_")
    dist = f"{stem}-{version}.dist-info"
    meta = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n"
    files = {f"{stem}_fake/__init__.py": "import sys\ndef main():\n    print('fake dct', *sys.argv[1:])\n"}
    if name == "dct-controller":
        meta += "Provides-Extra: ros\n" + "".join(f'Requires-Dist: {n}=={v}; extra == "ros"\n' for n, v in ros_extra)
        files[f"{dist}/entry_points.txt"] = "[console_scripts]\ndct = dct_controller_fake:main\n"
    files[f"{dist}/METADATA"] = meta
    files[f"{dist}/WHEEL"] = "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    record = []
    for name, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(text.encode())}")
    record.append(f"{dist}/RECORD,,")
    path = folder / f"{stem}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
        z.writestr(f"{dist}/RECORD", "\n".join(record) + "\n")
    return path


def fake_builder(calls=None, ros_wheels=True):
    """The wheelhouse: the project's fake wheel and, unless told not to, a fake wheel for each
    package of the ros extra (what pip download brings for --ros wheels)."""
    def build(source, wheelhouse):
        if calls is not None:
            calls.append(wheelhouse)
        fake_wheel(wheelhouse)
        for name, version in ROS_EXTRA if ros_wheels else ():
            fake_wheel(wheelhouse, name, version)
    return build


@pytest.fixture(scope="module")
def fake_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("bundle")
    res = B.build_bundle(d / "dct-bundle.tar.gz", wheelhouse_builder=fake_builder())
    with tarfile.open(res.path) as tar:
        tar.extractall(d / "x", filter="data")
    return res, d / "x" / res.folder


def run_install(folder: Path, target: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(folder / "install.sh"), str(target), *args], capture_output=True, text=True,
                          timeout=600)


def test_bundle_is_one_folder_with_a_manifest_of_every_file(fake_bundle):
    res, folder = fake_bundle
    with tarfile.open(res.path) as tar:
        tops = {m.name.split("/")[0] for m in tar.getmembers()}
    assert tops == {res.folder} and res.folder == f"dct-bundle-{VERSION}"
    manifest = json.loads((folder / "MANIFEST.json").read_text())
    listed = {f["path"]: f for f in manifest["files"]}
    on_disk = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()} - {"MANIFEST.json"}
    assert set(listed) == on_disk
    for path, f in listed.items():
        assert hashlib.sha256((folder / path).read_bytes()).hexdigest() == f["sha256"]
    assert {"install.sh", "README.txt", "systemd/dct-controller.service", "robot/robot.yaml",
            "robot/calibration.yaml", "robot/config.yaml", "robot/models/limo_distance_net.pt"} <= on_disk
    assert manifest["target"] == {"machine": "x86_64", "python": "3.11", "glibc": "2.35"}
    assert manifest["robot"] == "limo" and os.access(folder / "install.sh", os.X_OK)
    assert (folder / "robot" / "robot.yaml").read_bytes() == LIMO.read_bytes()
    assert "nominal" in yaml.safe_load((folder / "robot" / "calibration.yaml").read_text())["provenance"]["method"]


def test_unit_has_restart_watchdog_rtprio_affinity_and_preflight(fake_bundle):
    unit = (fake_bundle[1] / "systemd" / "dct-controller.service").read_text()
    for line in ("Type=notify", "WatchdogSec=2", "Restart=on-failure", "LimitRTPRIO=50", "CPUAffinity=0 1",
                 "ExecStartPre=@TARGET@/venv/bin/dct preflight", "ExecStart=@TARGET@/venv/bin/dct run",
                 "KillSignal=SIGINT", "--manifest @TARGET@/MANIFEST.json"):
        assert line in unit
    assert "@@" not in unit


def test_install_offline_into_a_fresh_venv(fake_bundle, tmp_path):
    folder = fake_bundle[1]
    # A space would be split (and a % expanded) by systemd in the unit's ExecStart: refused.
    refused = run_install(folder, tmp_path / "robot computer" / "dct")
    assert refused.returncode == 2 and "has a space or a %" in refused.stderr
    target = tmp_path / "robot_computer" / "dct"
    done = run_install(folder, target)
    assert done.returncode == 0, done.stderr
    assert "files match MANIFEST.json" in done.stdout
    dct = target / "venv" / "bin" / "dct"
    assert subprocess.run([str(dct), "hello"], capture_output=True, text=True).stdout.strip() == "fake dct hello"
    unit = (target / "systemd" / "dct-controller.service").read_text()
    assert f"ExecStart={target}/venv/bin/dct run" in unit and "@TARGET@" not in unit
    assert (target / "robot" / "models" / "limo_distance_net.pt").is_file() and (target / "logs").is_dir()
    # A second install refuses to replace it without --force, then replaces it with --force.
    again = run_install(folder, target)
    assert again.returncode == 1 and "already exists; pass --force" in again.stderr
    assert run_install(folder, target, "--force").returncode == 0


def test_install_refuses_a_changed_or_extra_file(fake_bundle, tmp_path):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(fake_bundle[1], folder)
    wheel = next((folder / "wheelhouse").glob("*.whl"))
    wheel.write_bytes(wheel.read_bytes() + b"x")
    (folder / "robot" / "extra.yaml").write_text("a: 1\n")
    done = run_install(folder, tmp_path / "t")
    assert done.returncode == 1 and not (tmp_path / "t").exists()
    assert "does not match its MANIFEST.json, refusing to install" in done.stderr
    assert f"wheelhouse/{wheel.name}: size" in done.stderr and "robot/extra.yaml: not in the manifest" in done.stderr
    usage = subprocess.run(["bash", str(folder / "install.sh")], capture_output=True, text=True)
    assert usage.returncode == 2 and "usage:" in usage.stderr


def test_output_path_is_checked_before_the_long_work(tmp_path):
    calls = []
    existing = tmp_path / "b.tar.gz"
    existing.write_bytes(b"old")
    with pytest.raises(B.BundleError, match="already exists; choose another name or pass --force"):
        B.build_bundle(existing, wheelhouse_builder=fake_builder(calls))
    with pytest.raises(B.BundleError, match="does not exist"):
        B.build_bundle(tmp_path / "nope" / "b.tar.gz", wheelhouse_builder=fake_builder(calls))
    with pytest.raises(B.BundleError, match=r"\.tar\.gz archive"):
        B.build_bundle(tmp_path / "b.zip", wheelhouse_builder=fake_builder(calls))
    assert calls == [] and existing.read_bytes() == b"old"
    res = B.build_bundle(existing, wheelhouse_builder=fake_builder(calls), force=True)
    assert res.path == existing and tarfile.is_tarfile(existing) and len(calls) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["b.tar.gz"]      # no temporary file left behind


def test_files_that_fail_preflight_are_refused(tmp_path):
    robot = yaml.safe_load(LIMO.read_text())
    robot["footprint"]["length_m"] = 0.40
    (tmp_path / "big.yaml").write_text(yaml.safe_dump(robot))
    with pytest.raises(B.BundleError, match="refusing to bundle files that fail preflight: distance_net: wrong model"):
        B.build_bundle(tmp_path / "b.tar.gz", B.BundleInputs(robot=tmp_path / "big.yaml"),
                       wheelhouse_builder=fake_builder())
    assert not (tmp_path / "b.tar.gz").exists()


def test_a_cuda_torch_is_refused(tmp_path):
    def cuda(source, wheelhouse):
        fake_wheel(wheelhouse)
        (wheelhouse / "torch-2.13.0-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"")
        (wheelhouse / "nvidia_cublas_cu12-12.8-py3-none-manylinux_2_27_x86_64.whl").write_bytes(b"")

    with pytest.raises(B.BundleError, match="CUDA torch"):
        B.build_bundle(tmp_path / "b.tar.gz", wheelhouse_builder=cuda)
    assert list(tmp_path.iterdir()) == []


def test_manylinux_platforms_cover_older_tags():
    tags = B.manylinux_platforms("2.28")
    assert tags[0] == "manylinux_2_28_x86_64" and "manylinux_2_17_x86_64" in tags and "manylinux2014_x86_64" in tags
    with pytest.raises(B.BundleError):
        B.manylinux_platforms("2.5")


def test_sd_notify_ready_and_rate_limited_watchdog(tmp_path):
    addr = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(addr)
    server.settimeout(2)
    now = [0.0]
    n = SystemdNotifier({"NOTIFY_SOCKET": addr, "WATCHDOG_USEC": "2000000"}, clock=lambda: now[0])
    assert n.enabled and n.watchdog_s == 2.0
    assert n.ready("loop running")
    assert server.recv(100) == b"READY=1\nSTATUS=loop running"
    assert n.watchdog() and not n.watchdog()        # the second within 0.5 s is skipped
    now[0] = 0.6
    assert n.watchdog()
    assert [server.recv(100), server.recv(100)] == [b"WATCHDOG=1", b"WATCHDOG=1"]
    off = SystemdNotifier({})
    assert not off.enabled and not off.ready() and not off.watchdog()
    n.close()
    server.close()


@pytest.mark.slow
@pytest.mark.realtime
def test_real_bundle_installs_offline_and_preflight_passes(tmp_path):
    """The whole path: build (pip), unpack, install offline, run the installed dct preflight
    against the simulator (`dct hil serve`: the emulated base on udp_multicast, the sensor
    topics over DDS). Prints the figures. Real time: the preflight judges the sensors' stamps
    against this computer's clock, and a simulator sharing its two cores with another test runs
    late (its stamps a second behind), which the preflight rightly refuses."""
    t = time.perf_counter()
    res = B.build_bundle(tmp_path / "dct-bundle.tar.gz", echo=print)
    build_s = time.perf_counter() - t
    t = time.perf_counter()
    with tarfile.open(res.path) as tar:
        tar.extractall(tmp_path / "x", filter="data")
    unpack_s = time.perf_counter() - t
    folder = tmp_path / "x" / res.folder
    target = tmp_path / "target"
    t = time.perf_counter()
    done = run_install(folder, target)
    install_s = time.perf_counter() - t
    assert done.returncode == 0, done.stderr[-2000:]
    wheels = json.loads((folder / "MANIFEST.json").read_text())["wheels"]
    assert any(w.startswith("torch-2.13.0+cpu") for w in wheels)
    robot = target / "robot"
    port, domain = unique_port(), unique_domain()
    # the simulator as its own process (dct hil serve, from this checkout): the emulated base on
    # udp_multicast and the sensors as the drivers' DDS topics, as the robot would present them
    serve = subprocess.Popen([sys.executable, "-m", "runtime.app.cli", "hil", "serve", "case3", "--no-oracle",
                              "--camera-rate", "15", "--domain-id", str(domain), "--can-port", str(port),
                              "--connect-timeout", "600"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    try:
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in serve.stdout] + [lines.put(None)],
                         daemon=True).start()  # reads it to the end: the pipe never fills
        deadline, said = time.monotonic() + 180, []
        while not any(" serving:" in x for x in said):
            try:
                line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                pytest.fail("dct hil serve said nothing about serving in 180 s: " + "".join(said)[-2000:])
            if line is None:
                pytest.fail("dct hil serve ended before serving: " + "".join(said)[-2000:])
            said.append(line)
        t = time.perf_counter()
        pre = subprocess.run([str(target / "venv" / "bin" / "dct"), "preflight", "--robot", str(robot / "robot.yaml"),
                              "--calibration", str(robot / "calibration.yaml"), "--config", str(robot / "config.yaml"),
                              "--can-interface", "udp_multicast", "--can-udp-port", str(port),
                              "--ros-domain", str(domain), "--log-dir", str(target / "logs"), "--min-free-gb", "0.1",
                              "--json", str(target / "logs" / "preflight.json")],
                             capture_output=True, text=True, timeout=300, cwd=tmp_path)
        preflight_s = time.perf_counter() - t
    finally:
        serve.terminate()
        serve.wait(30)
    print(pre.stdout)
    print(f"bundle {res.size_bytes / 1e6:.0f} MB, {res.wheels} wheels: build {build_s:.1f} s, unpack {unpack_s:.1f} s, "
          f"install {install_s:.1f} s, preflight {preflight_s:.1f} s")
    assert pre.returncode == 0, pre.stdout + pre.stderr
    doc = json.loads((target / "logs" / "preflight.json").read_text())
    names = {c["name"]: c for c in doc["checks"]}
    assert all(names[n]["ok"] for n in ("base", "can_link", "topic:lidar", "topic:imu", "distance_net", "ros:install",
                                        "ros:middleware", "match:lidar", "match:imu"))
    assert "from the bundle's venv" in names["ros:install"]["message"]      # --ros wheels, the default
    assert "site-packages/models/artifacts" in names["distance_net"]["message"]


# ----------------------------------------------------------------------------- ROS 2 in the bundle


def python_312() -> str | None:
    """A CPython 3.12 to install a --ros system bundle with (Jazzy's rclpy is built for it)."""
    import glob
    import shutil

    root = os.environ.get("PYENV_ROOT", os.path.expanduser("~/.pyenv"))
    for cand in [shutil.which("python3.12"), *sorted(glob.glob(f"{root}/versions/3.12*/bin/python3.12"))]:
        if cand and subprocess.run([cand, "-c", "import venv"], capture_output=True).returncode == 0:
            return cand
    return None


def test_ros_wheels_are_carried_recorded_and_installed(fake_bundle, tmp_path):
    """The default: the ros extra's wheels go into the wheelhouse, the manifest says so, and
    install.sh installs dct-controller[ros], so rclpy lands in the venv."""
    folder = fake_bundle[1]
    manifest = json.loads((folder / "MANIFEST.json").read_text())
    assert manifest["format"] == 2
    assert manifest["ros"] == {"mode": "wheels", "distro": "jazzy", "wheels": [f"{n}=={v}" for n, v in ROS_EXTRA]}
    assert any(n == "ros-jazzy-rclpy" for n, _ in ROS_EXTRA)
    assert '"dct-controller[ros]==' in (folder / "install.sh").read_text()
    target = tmp_path / "dct"
    done = run_install(folder, target)
    assert done.returncode == 0, done.stderr
    got = subprocess.run([str(target / "venv" / "bin" / "python"), "-c",
                          "import importlib.metadata as m; print(m.version('ros-jazzy-rclpy'))"],
                         capture_output=True, text=True)
    assert got.stdout.strip() == dict(ROS_EXTRA)["ros-jazzy-rclpy"]
    assert "--manifest " + str(target / "MANIFEST.json") in done.stdout and not (target / "bin").exists()


def test_ros_wheels_missing_from_the_wheelhouse_are_refused(tmp_path):
    with pytest.raises(B.BundleError, match=r"--ros wheels: the wheelhouse lacks ros-jazzy-rclpy==[\d.]+"):
        B.build_bundle(tmp_path / "b.tar.gz", wheelhouse_builder=fake_builder(ros_wheels=False))
    assert list(tmp_path.iterdir()) == []
    # --ros none does not want them
    res = B.build_bundle(tmp_path / "b.tar.gz", ros="none", wheelhouse_builder=fake_builder(ros_wheels=False))
    with tarfile.open(res.path) as tar:
        manifest = json.load(tar.extractfile(f"{res.folder}/MANIFEST.json"))
        install = tar.extractfile(f"{res.folder}/install.sh").read().decode()
    assert manifest["ros"] == {"mode": "none", "distro": "jazzy"}
    assert '"dct-controller==' in install and "[ros]" not in install


def test_ros_modes_that_cannot_work_are_refused_before_the_long_work(tmp_path):
    calls = []
    shipped = yaml.safe_load(Path(str(resources.files("runtime") / "config" / "default.yaml")).read_text())
    rclpy_cfg = tmp_path / "rclpy.yaml"
    rclpy_cfg.write_text(yaml.safe_dump({**shipped, "ros": {**shipped["ros"], "middleware": "rclpy"}}))
    with pytest.raises(B.BundleError, match="--ros none carries no rclpy, but the config asks for ros.middleware: rclpy"):
        B.build_bundle(tmp_path / "b.tar.gz", B.BundleInputs(config=rclpy_cfg), ros="none",
                       wheelhouse_builder=fake_builder(calls))
    sec_cfg = tmp_path / "sec.yaml"
    sec_cfg.write_text(yaml.safe_dump({**shipped, "ros": {**shipped["ros"], "security": {"keystore": "/k"}}}))
    with pytest.raises(B.BundleError, match="ros.security .* --ros wheels has none .* use --ros system"):
        B.build_bundle(tmp_path / "b.tar.gz", B.BundleInputs(config=sec_cfg), wheelhouse_builder=fake_builder(calls))
    with pytest.raises(B.BundleError, match=r"built for CPython 3\.12.*--python-version 3\.12 \(got 3\.11\)"):
        B.build_bundle(tmp_path / "b.tar.gz", ros="system", wheelhouse_builder=fake_builder(calls))
    with pytest.raises(B.BundleError, match="--ros 'apt'"):
        B.build_bundle(tmp_path / "b.tar.gz", ros="apt", wheelhouse_builder=fake_builder(calls))
    assert calls == [] and set(tmp_path.iterdir()) == {rclpy_cfg, sec_cfg}      # no archive, nothing built


@pytest.fixture(scope="module")
def system_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("system")
    res = B.build_bundle(d / "dct-bundle.tar.gz", ros="system", python_version="3.12",
                         wheelhouse_builder=fake_builder(ros_wheels=False))
    with tarfile.open(res.path) as tar:
        tar.extractall(d / "x", filter="data")
    return d / "x" / res.folder


def test_ros_system_unit_runs_dct_through_the_env_script(system_bundle):
    folder = system_bundle
    manifest = json.loads((folder / "MANIFEST.json").read_text())
    assert manifest["ros"] == {"mode": "system", "distro": "jazzy", "setup": "/opt/ros/jazzy/setup.bash"}
    assert manifest["target"]["python"] == "3.12" and not any("ros_jazzy" in w for w in manifest["wheels"])
    unit = (folder / "systemd" / "dct-controller.service").read_text()
    assert "ExecStartPre=@TARGET@/bin/dct-env @TARGET@/venv/bin/dct preflight" in unit
    assert "ExecStart=@TARGET@/bin/dct-env @TARGET@/venv/bin/dct run" in unit
    assert "--manifest @TARGET@/MANIFEST.json" in unit and "/opt/ros/jazzy/setup.bash" in unit
    env = folder / "bin" / "dct-env"
    assert os.access(env, os.X_OK) and 'source "$DCT_ROS_SETUP"' in env.read_text() and "@@" not in env.read_text()
    install = (folder / "install.sh").read_text()
    assert '"dct-controller==' in install and "[ros]" not in install


def test_ros_system_install_needs_the_robots_ros_and_sources_it(system_bundle, tmp_path):
    py = python_312()
    if py is None:
        pytest.skip("no CPython 3.12 here to install a --ros system bundle with")
    env = {**os.environ, "PYTHON": py, "ROS_SETUP": str(tmp_path / "no_ros" / "setup.bash")}
    done = subprocess.run(["bash", str(system_bundle / "install.sh"), str(tmp_path / "t")], capture_output=True,
                          text=True, env=env, timeout=600)
    assert done.returncode == 1 and "does not exist: install ROS 2 jazzy" in done.stderr
    assert not (tmp_path / "t" / "venv").exists()
    setup = tmp_path / "ros" / "setup.bash"          # a stand-in for /opt/ros/jazzy/setup.bash
    setup.parent.mkdir()
    setup.write_text("export ROS_DISTRO=jazzy\nexport AMENT_PREFIX_PATH=/opt/ros/jazzy\n")
    target = tmp_path / "t"
    done = subprocess.run(["bash", str(system_bundle / "install.sh"), str(target)], capture_output=True, text=True,
                          env={**env, "ROS_SETUP": str(setup)}, timeout=600)
    assert done.returncode == 0, done.stderr
    assert f"controller:   {target}/bin/dct-env {target}/venv/bin/dct" in done.stdout
    ran = subprocess.run([str(target / "bin" / "dct-env"), "bash", "-c", 'echo "$ROS_DISTRO $DCT_ROS_SETUP"'],
                         capture_output=True, text=True)
    assert ran.stdout.strip() == f"jazzy {setup}"
    ran = subprocess.run([str(target / "bin" / "dct-env"), str(target / "venv" / "bin" / "dct"), "hello"],
                         capture_output=True, text=True)
    assert ran.stdout.strip() == "fake dct hello"
    unit = (target / "systemd" / "dct-controller.service").read_text()
    assert f"ExecStart={target}/bin/dct-env {target}/venv/bin/dct run" in unit and "@TARGET@" not in unit
