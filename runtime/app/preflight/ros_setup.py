"""Preflight's checks of the ROS 2 set-up, before any topic is heard: `ros:install` (the ROS 2
the bundle was built for: its wheels in the venv, the robot's own install, or none),
`ros:middleware` (which middleware `dct run` will use, and rclpy's version or why it does not
import), `ros:discovery` (who can reach the controller's topics, the goal topic among them) and
`ros:security` (SROS2's keystore and enclave, or that goals are unauthenticated)."""
from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from runtime.app.preflight.check import Check, one_line

#: What an SROS2 enclave folder (`ros2 security create_enclave`) must hold for a node to start.
ENCLAVE_FILES = ("cert.pem", "key.pem", "governance.p7s", "permissions.p7s")
ROS_INSTALL_MODES = ("wheels", "system", "none")
_ENCLAVE = re.compile(r"^(/[A-Za-z0-9_]+)+$")
_DISTRO = re.compile(r"^[a-z]+$")


def rclpy_origin() -> str | None:
    """The file rclpy would import from, without importing it (None: not found)."""
    try:
        spec = importlib.util.find_spec("rclpy")
    except (ImportError, ValueError):
        return None
    return None if spec is None else spec.origin


def cyclonedds_routed(inputs: Any) -> list[str]:
    """The input types that rclpy has no Python package for here (carried by a cyclonedds
    participant in the same process, runtime.io.ros.rclpy_transport)."""
    from runtime.io.ros.rclpy_transport import ros_message_class

    types = sorted({t.type for s in ("lidar", "imu", "camera", "goal") if (t := getattr(inputs, s, None)) is not None})
    return [t for t in types if ros_message_class(t) is None]


# ----------------------------------------------------------------------------- ros:middleware


def resolve(ros: Any, available: Callable[[], tuple[bool, str]]) -> tuple[str | None, bool, str]:
    """(middleware dct run will use or None when it cannot start, rclpy imports, rclpy's version
    or why not), as runtime.io.ros.transport.resolve_middleware decides."""
    ok, why = available()
    if ros.middleware == "cyclonedds":
        return "cyclonedds", ok, why
    if ros.middleware == "rclpy" and not ok:
        return None, ok, why
    return ("rclpy" if ok else "cyclonedds"), ok, why


def check_middleware(ros: Any, available: Callable[[], tuple[bool, str]] | None = None) -> Check:
    """`ros:middleware`: the middleware, rclpy's version and where it comes from, or why not."""
    from runtime.io.ros.transport import rclpy_available

    which, ok, why = resolve(ros, available or rclpy_available)
    name = "ros:middleware"
    if which is None:
        return Check(name, "FAIL", f"ros.middleware rclpy, but rclpy does not import ({why})",
                     "source the robot's ROS 2 (source /opt/ros/jazzy/setup.bash), install the ROS 2 wheels "
                     "(pip install 'dct-controller[ros]', or a bundle built with --ros wheels), or set "
                     "ros.middleware: cyclonedds")
    if which == "cyclonedds":
        note = "rclpy is not used" if ok else f"rclpy does not import: {why}"
        how = "ros.middleware cyclonedds" if ros.middleware == "cyclonedds" else "ros.middleware auto -> cyclonedds"
        return Check(name, "PASS", f"{how} ({note})")
    origin = rclpy_origin()
    routed = cyclonedds_routed(ros.inputs)
    extra = f"; {', '.join(routed)} through cyclonedds (no Python package for rclpy)" if routed else ""
    return Check(name, "PASS", f"ros.middleware {ros.middleware}{' -> rclpy' if ros.middleware == 'auto' else ''}: "
                 f"{why}" + (f" from {Path(origin).parent}" if origin else "") + extra)


# ----------------------------------------------------------------------------- ros:discovery


def discovery_reach(ros: Any, middleware: str | None, environ: Mapping[str, str] = os.environ) -> tuple[str, str]:
    """("localhost" | "network", why) for what the controller's participants will actually do
    (runtime.io.ros.transport.effective_discovery, except that a cyclonedds participant does not
    read rclpy's environment variables)."""
    from runtime.io.ros.transport import effective_discovery

    where, why = effective_discovery(ros.discovery, environ)
    if where == "localhost" and ros.discovery == "subnet":
        routed = [] if middleware != "rclpy" else cyclonedds_routed(ros.inputs)
        if middleware == "cyclonedds" or routed:
            what = "the middleware is cyclonedds" if middleware == "cyclonedds" else \
                f"the cyclonedds participant that carries {', '.join(routed)}"
            return "network", f"{why} is set, but {what}, which does not read it"
    return where, why


def check_discovery(ros: Any, middleware: str | None, environ: Mapping[str, str] = os.environ) -> Check:
    """`ros:discovery`: open to the network is a WARN (any host there can publish a goal)."""
    name = "ros:discovery"
    domain, goal = ros.inputs.domain_id, ros.inputs.goal.topic if ros.inputs.goal is not None else None
    where, why = discovery_reach(ros, middleware, environ)
    if where == "localhost":
        return Check(name, "PASS", f"this computer only ({why}): no other host can see the topics"
                     + (f" or publish on {goal}" if goal else ""))
    uri = " (CYCLONEDDS_URI is set: its interfaces and peers decide for cyclonedds)" \
        if environ.get("CYCLONEDDS_URI") and middleware != "rclpy" else ""
    said = f"any host on the network that joins DDS domain {domain} can publish a goal on {goal} and the robot " \
           "drives to it" if goal else f"any host on the network can see the topics of DDS domain {domain}"
    fix = ("everything on this computer: ros.discovery: localhost (rclpy alone also honours "
           "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST); goals from other computers: keep them on a trusted network "
           "and allow only the operator's enclave to publish them with SROS2 (ros.security)")
    return Check(name, "WARN", f"open to the network ({why}){uri}: {said}", fix)


# ----------------------------------------------------------------------------- ros:security


def check_security(ros: Any, middleware: str | None, discovery_where: str) -> Check:
    """`ros:security`: the keystore, the enclave's files and rclpy; or goals are unauthenticated."""
    name = "ros:security"
    sec = ros.security
    goal = ros.inputs.goal.topic if ros.inputs.goal is not None else "the goal topic"
    if sec is None:
        msg = f"off (ros.security not set): goals on {goal} are not authenticated"
        if discovery_where == "localhost":
            return Check(name, "PASS", msg + "; only processes on this computer can send them")
        return Check(name, "WARN", msg + f"; any participant that reaches domain {ros.inputs.domain_id} can send "
                     "one", "ros.security: {keystore: <folder>, enclave: /dct_controller} with a ROS 2 built with "
                     "DDS Security, or ros.discovery: localhost")
    keystore = Path(sec.keystore)
    if not _ENCLAVE.match(sec.enclave):
        return Check(name, "FAIL", f"ros.security.enclave {sec.enclave!r} is not an enclave name (e.g. "
                     "/dct_controller)", "name the enclave as `ros2 security create_enclave` did")
    if not keystore.is_dir():
        return Check(name, "FAIL", f"ros.security.keystore {keystore} is not a folder",
                     f"ros2 security create_keystore {keystore}, then ros2 security create_enclave {keystore} "
                     f"{sec.enclave}")
    enclave = keystore / "enclaves" / sec.enclave.lstrip("/")
    missing = [f for f in ENCLAVE_FILES if not (enclave / f).is_file()]
    if missing:
        return Check(name, "FAIL", f"enclave {sec.enclave} in {keystore}: {', '.join(missing)} missing from "
                     f"{enclave}", f"ros2 security create_enclave {keystore} {sec.enclave}")
    if middleware != "rclpy":
        return Check(name, "FAIL", f"ros.security is set, but the middleware is {middleware or 'not available'}: "
                     "only rclpy runs SROS2 here", "ros.middleware: rclpy with a ROS 2 built with DDS Security "
                     "(the robot's ROS 2: a bundle built with --ros system)")
    return Check(name, "PASS", f"SROS2 enclave {sec.enclave} in {keystore} ({', '.join(ENCLAVE_FILES)}); "
                 "enforced: a ROS 2 without DDS Security refuses to start (see the topic lines)")


# ----------------------------------------------------------------------------- ros:install


class ManifestError(ValueError):
    """MANIFEST.json cannot say how ROS 2 was installed; the message names the file and field."""


@dataclass(frozen=True)
class RosInstall:
    """How the bundle installed ROS 2 (MANIFEST.json's `ros`)."""

    mode: str                   # wheels | system | none
    distro: str = "jazzy"
    source: str = ""            # the manifest it came from


def default_manifest() -> Path:
    """Where install.sh puts the bundle's manifest: beside the venv this process runs from."""
    return Path(sys.prefix).parent / "MANIFEST.json"


def read_ros_install(path: str | Path) -> RosInstall:
    """MANIFEST.json's `ros` section; a bundle from before it carried no ROS 2 (`none`)."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ManifestError(f"{path}: cannot be read as JSON ({one_line(exc)[:120]})") from None
    if not isinstance(doc, dict) or "files" not in doc:
        raise ManifestError(f"{path}: not a dct deploy bundle's MANIFEST.json (no files list)")
    ros = doc.get("ros")
    if ros is None:
        return RosInstall("none", source=str(path))
    if not isinstance(ros, dict):
        raise ManifestError(f"{path}: ros must be an object, got {type(ros).__name__}")
    mode, distro = ros.get("mode"), ros.get("distro", "jazzy")
    if mode not in ROS_INSTALL_MODES:
        raise ManifestError(f"{path}: ros.mode must be one of {', '.join(ROS_INSTALL_MODES)}, got {mode!r}")
    if not isinstance(distro, str) or not _DISTRO.match(distro):
        raise ManifestError(f"{path}: ros.distro must be a ROS 2 distribution name (e.g. jazzy), got {distro!r}")
    return RosInstall(mode, distro, str(path))


_IMPORT_RCLPY = "import rclpy, rclpy.impl.implementation_singleton; print(rclpy.__file__)"


def _import_after_sourcing(setup: Path, python: str) -> tuple[bool, str]:
    """Source `setup` in bash, then import rclpy with `python`: (ok, rclpy's file or why not)."""
    script = 'source "$1" >/dev/null 2>&1 || { echo "sourcing $1 failed" >&2; exit 3; }; exec "$2" -c "$3"'
    try:
        done = subprocess.run(["bash", "-c", script, "bash", str(setup), python, _IMPORT_RCLPY],
                              capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError) as exc:
        return False, one_line(exc)
    if done.returncode == 0:
        return True, done.stdout.strip().splitlines()[-1] if done.stdout.strip() else "?"
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    return False, (lines[-1] if lines else f"exit {done.returncode}")[:200]


def check_ros_install(install: RosInstall, ros: Any, *, available: Callable[[], tuple[bool, str]] | None = None,
                      environ: Mapping[str, str] = os.environ, python: str = sys.executable,
                      prefix: str = sys.prefix) -> Check:
    """`ros:install`: what the bundle's ROS 2 mode needs is here.

    wheels: rclpy imports, from this venv; system: the setup script exists and rclpy imports
    after sourcing it (DCT_ROS_SETUP, set by the bundle's bin/dct-env, else
    /opt/ros/<distro>/setup.bash); none: cyclonedds, and the config does not ask for rclpy.
    """
    from runtime.io.ros.transport import rclpy_available

    name, where = "ros:install", f"(bundle built with --ros {install.mode}, {install.source})"
    if install.mode == "wheels":
        ok, why = (available or rclpy_available)()
        if not ok:
            return Check(name, "FAIL", f"the ROS 2 wheels do not import: {why} {where}",
                         "reinstall the bundle (install.sh TARGET --force)")
        origin = rclpy_origin() or ""
        if not Path(origin).resolve().is_relative_to(Path(prefix).resolve()):
            return Check(name, "WARN", f"{why} imports from {origin}, not from this venv {prefix} {where}: a sourced "
                         "ROS 2 shadows the bundle's wheels", "run dct without sourcing /opt/ros/*/setup.bash")
        return Check(name, "PASS", f"{why} from the bundle's venv {where}")
    if install.mode == "system":
        setup = Path(environ.get("DCT_ROS_SETUP") or f"/opt/ros/{install.distro}/setup.bash")
        if not setup.is_file():
            return Check(name, "FAIL", f"{setup} does not exist: no ROS 2 {install.distro} here {where}",
                         f"install ROS 2 {install.distro} (apt install ros-{install.distro}-ros-base), or set "
                         "ROS_SETUP when running install.sh, or rebuild the bundle with --ros wheels")
        ok, what = _import_after_sourcing(setup, python)
        if not ok:
            return Check(name, "FAIL", f"rclpy does not import after sourcing {setup}: {what} {where}",
                         f"the venv's CPython must be the one ROS 2 {install.distro} is built for; check "
                         f"`source {setup} && python3 -c 'import rclpy'`")
        return Check(name, "PASS", f"rclpy imports after sourcing {setup} ({what}) {where}")
    if ros.middleware == "rclpy":
        return Check(name, "FAIL", f"the config asks for ros.middleware rclpy, but the bundle carries no ROS 2 "
                     f"{where}", "rebuild the bundle with --ros wheels or --ros system, or set ros.middleware: "
                     "cyclonedds")
    try:
        from importlib.metadata import version

        return Check(name, "PASS", f"cyclonedds {version('cyclonedds')} (no rclpy in the bundle) {where}")
    except Exception as exc:  # noqa: BLE001 - PackageNotFoundError, a broken install
        return Check(name, "FAIL", f"cyclonedds is not installed ({one_line(exc)}) {where}",
                     "reinstall the bundle (install.sh TARGET --force)")


#: What the rclpy node's Fast DDS profile asks for (runtime/io/ros/fastdds_profile.xml); the kernel
#: caps a socket's buffer at these limits without an error.
SOCKET_BUFFER_BYTES = 4 * 1024 * 1024


def check_socket_buffers(middleware: str | None, sys_root: str | Path = "/") -> Check:
    """`ros:buffers`: the kernel's UDP buffer limits, which decide whether camera-sized best-effort
    samples from another host arrive (below them DDS drops fragments of a 0.9 MB image)."""
    limits = {}
    for name in ("rmem_max", "wmem_max"):
        try:
            limits[name] = int((Path(sys_root) / "proc/sys/net/core" / name).read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return Check("ros:buffers", "WARN", f"net.core.{name} could not be read",
                         "check that /proc/sys/net/core is readable")
    low = [f"net.core.{k} {v // 1024} kB" for k, v in limits.items() if v < SOCKET_BUFFER_BYTES]
    if not low:
        return Check("ros:buffers", "PASS", "net.core.rmem_max / wmem_max "
                     f"{limits['rmem_max'] // 1024} / {limits['wmem_max'] // 1024} kB: camera images over UDP fit")
    return Check("ros:buffers", "WARN",
                 f"{', '.join(low)} (< {SOCKET_BUFFER_BYTES // 1024} kB): best-effort images from other hosts lose "
                 f"fragments ({middleware or 'DDS'} asks for {SOCKET_BUFFER_BYTES // 1024} kB)",
                 f"sysctl -w net.core.rmem_max={SOCKET_BUFFER_BYTES} net.core.wmem_max={SOCKET_BUFFER_BYTES} "
                 "(and in /etc/sysctl.d/ to keep it)")
