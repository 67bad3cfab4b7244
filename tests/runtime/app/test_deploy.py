"""dct deploy bundle and its install.sh.

Fast tests build the bundle with a tiny fake wheelhouse (one pure-Python wheel named
dct-controller that provides a `dct` script) and run the real install.sh into a fresh venv:
manifest, offline install, refusal of a changed file, output-path rules, the unit's contents.
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


def fake_wheel(folder: Path) -> Path:
    """A valid pure-Python wheel dct_controller-VERSION whose `dct` prints its arguments."""
    dist = f"dct_controller-{VERSION}.dist-info"
    files = {
        "dct_fake/__init__.py": "import sys\ndef main():\n    print('fake dct', *sys.argv[1:])\n",
        f"{dist}/METADATA": f"Metadata-Version: 2.1\nName: dct-controller\nVersion: {VERSION}\n",
        f"{dist}/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
        f"{dist}/entry_points.txt": "[console_scripts]\ndct = dct_fake:main\n",
    }
    record = []
    for name, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(text.encode())}")
    record.append(f"{dist}/RECORD,,")
    path = folder / f"dct_controller-{VERSION}-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
        z.writestr(f"{dist}/RECORD", "\n".join(record) + "\n")
    return path


def fake_builder(calls=None):
    def build(source, wheelhouse):
        if calls is not None:
            calls.append(wheelhouse)
        fake_wheel(wheelhouse)
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
                 "KillSignal=SIGINT"):
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
def test_real_bundle_installs_offline_and_preflight_passes(tmp_path):
    """The whole path: build (pip), unpack, install offline, run the installed dct preflight
    against the simulator (`dct hil serve`: the emulated base on udp_multicast, the sensor
    topics over DDS). Prints the figures."""
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
    assert all(names[n]["ok"] for n in ("base", "can_link", "topic:lidar", "topic:imu", "distance_net"))
    assert "site-packages/models/artifacts" in names["distance_net"]["message"]
