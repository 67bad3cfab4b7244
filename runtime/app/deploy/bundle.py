"""`dct deploy bundle`: everything the robot's computer needs to install the controller offline.

The archive unpacks into ONE folder, `dct-bundle-<version>/`, holding:
- `install.sh TARGET`: checks the computer and MANIFEST.json, makes TARGET/venv and installs
  from the wheelhouse with `pip install --no-index --find-links` (templates.py);
- `wheelhouse/`: the project as a wheel (`pip wheel --no-deps`, built from a copy of the tracked
  source files, so that a stale build/ folder never leaks into it) and every dependency for the
  target, resolved from the project's pins by `pip download --only-binary=:all: --platform ...
  --python-version ...` (so the build machine's own Python and packages do not matter). torch
  must be the CPU build: a CUDA torch, or any nvidia-* / triton wheel, stops the build;
- `robot/`: robot.yaml, calibration.yaml, config.yaml, models/<distance net>, all checked with
  preflight's file checks before anything is built (a model for another footprint is refused).
  Without --calibration, a nominal calibration is made from the robot description (its
  provenance says so, and `dct preflight` WARNs until the robot is calibrated);
- `systemd/dct-controller.service`, `README.txt`, `MANIFEST.json` (sha256 and size per file, the
  target, the robot, and how ROS 2 comes: `ros`);
- ROS 2 (`ros`, MANIFEST.json's `ros.mode`): `wheels` (the default) puts the project's `ros` extra
  (ROS 2 Jazzy's rclpy with Fast DDS and the message packages, from pip) into the wheelhouse and
  install.sh installs `dct-controller[ros]`: the robot needs no ROS 2 of its own; `system` uses
  the robot's ROS 2 Jazzy: nothing of ROS 2 is installed, the venv is CPython 3.12 (what Jazzy's
  rclpy is built for) and the unit runs dct through `bin/dct-env`, which sources
  /opt/ros/jazzy/setup.bash; `none`: cyclonedds alone (always in the wheelhouse), no rclpy.

Output: the path is checked before the long work (folder exists and is writable, not an
existing file unless --force, ends in .tar.gz), and the archive is written to a temporary file
in the same folder, fsync'ed and renamed: an interrupted build leaves no half archive.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import platform
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata, resources
from pathlib import Path

from calibration.outputs import atomic_file
from runtime.app.deploy import templates

PROJECT = "dct-controller"
DEFAULT_PYTHON = "3.11"
#: Oldest glibc the wheelhouse may need; manylinux tags from this one down to manylinux2014 are
#: accepted (torch 2.13 CPU, mujoco, numpy need 2.27/2.28: Debian 12, Ubuntu 20.04+ have them).
DEFAULT_GLIBC = "2.35"
MACHINE = "x86_64"
#: Wheels that mean a CUDA torch came in: refused (several GB, no GPU on the NUC).
CUDA_WHEEL_PREFIXES = ("nvidia_", "nvidia-", "triton-", "triton_")
ARCHIVE_SUFFIX = ".tar.gz"
#: How the bundle brings ROS 2 (see the module docstring), and the ROS 2 it is for.
ROS_MODES = ("wheels", "system", "none")
DEFAULT_ROS = "wheels"
ROS_DISTRO = "jazzy"
#: The CPython a distribution's own rclpy is built for (its Ubuntu's python3): `system` needs it.
ROS_DISTRO_PYTHON = {"jazzy": "3.12"}


class BundleError(RuntimeError):
    """The bundle cannot be built; the message says why, on one line."""


@dataclass(frozen=True)
class BundleInputs:
    robot: Path | None = None
    calibration: Path | None = None
    config: Path | None = None


@dataclass
class BundleResult:
    path: Path
    folder: str
    files: int
    size_bytes: int
    wheels: int
    seconds: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- inputs


def project_root(start: Path | None = None) -> Path:
    """The source checkout this code runs from (pyproject.toml naming dct-controller)."""
    here = (start or Path(__file__)).resolve()
    for d in [here, *here.parents]:
        py = d / "pyproject.toml"
        if py.is_file() and f'name = "{PROJECT}"' in py.read_text(encoding="utf-8"):
            return d
    raise BundleError(f"no source checkout of {PROJECT} above {here}: run `dct deploy bundle` from a checkout "
                      "installed with `pip install -e .` (or pass source= to build_bundle)")


def check_out_path(out: Path, force: bool) -> Path:
    from calibration.outputs import OutputPathError, check_output_path

    if not str(out).endswith(ARCHIVE_SUFFIX):
        raise BundleError(f"--out {out}: the bundle is a {ARCHIVE_SUFFIX} archive; name it e.g. dct-bundle{ARCHIVE_SUFFIX}")
    try:
        return check_output_path(out, what="--out", overwrite=force)
    except OutputPathError as exc:
        raise BundleError(str(exc)) from None


def validate_inputs(inputs: BundleInputs):
    """Preflight's file checks: every FAIL stops the build; returns the loaded files."""
    from runtime.app.preflight.files import check_files

    files = check_files(inputs.robot, inputs.calibration, inputs.config)
    failed = [c for c in files.checks if c.status == "FAIL"]
    # No calibration given is fine here: a nominal one is made (the check WARNs or FAILs for that).
    failed = [c for c in failed if not (c.name == "calibration" and inputs.calibration is None)]
    if failed:
        raise BundleError("refusing to bundle files that fail preflight: "
                          + "; ".join(f"{c.name}: {c.text()}" for c in failed))
    return files


def nominal_calibration_yaml(robot) -> str:
    """A calibration from the robot description alone (the nominal sensors: K from the field of
    view, no distortion, T_cam<-lidar from the mounts); its provenance says it is nominal, so
    preflight WARNs until measured."""
    from calibration.calibration_file import calibration_yaml, make_calibration
    from calibration.sensor_calibration import nominal_sensors

    s = nominal_sensors(robot)
    cal = make_calibration(robot.name, s.camera.K, s.camera.dist, s.camera.width_px, s.camera.height_px,
                           s.T_cam_lidar,
                           method="nominal: from the robot description by dct deploy bundle (not calibrated)")
    return calibration_yaml(cal)


# ----------------------------------------------------------------------------- wheelhouse


def manylinux_platforms(glibc: str = DEFAULT_GLIBC, machine: str = MACHINE) -> list[str]:
    """pip's --platform list for a target glibc: pip does not expand manylinux_2_X tags to older
    ones by itself, so every tag the target accepts is named."""
    major, minor = (int(x) for x in glibc.split("."))
    if major != 2 or minor < 17:
        raise BundleError(f"glibc {glibc}: give 2.17 or newer (e.g. 2.35)")
    return ([f"manylinux_2_{m}_{machine}" for m in range(minor, 16, -1)]
            + [f"manylinux2014_{machine}", f"manylinux2010_{machine}", f"manylinux1_{machine}"])


def _pip(args: list[str], what: str, python: str = sys.executable) -> None:
    done = subprocess.run([python, "-m", "pip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        lines = [ln for ln in (done.stderr + done.stdout).splitlines()
                 if ln.strip() and not ln.startswith("WARNING: Location")]
        tail = " | ".join(lines[-4:])
        raise BundleError(f"{what} failed (pip exit {done.returncode}): {tail}")


def copy_source(root: Path, dest: Path) -> Path:
    """The tracked files of the checkout (git ls-files), else the tree without build outputs."""
    dest.mkdir(parents=True)
    try:
        listed = subprocess.run(["git", "-C", str(root), "ls-files", "-z"], capture_output=True, check=True).stdout
        names = [n for n in listed.decode().split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        names = []
    if names:
        for n in names:
            src = root / n
            if src.is_file():
                (dest / n).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dest / n)
    else:
        shutil.copytree(root, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", "out", ".pytest_cache"))
    return dest


def build_wheelhouse(source: Path, wheelhouse: Path, *, python_version: str = DEFAULT_PYTHON,
                     glibc: str = DEFAULT_GLIBC, extras: tuple[str, ...] = ()) -> None:
    """The project's wheel and every dependency for the target (with `extras`), into `wheelhouse`."""
    with tempfile.TemporaryDirectory(prefix="dct-src-") as tmp:
        src = copy_source(source, Path(tmp) / "src")
        _pip(["wheel", "--no-deps", "--quiet", "-w", str(wheelhouse), str(src)], "pip wheel (the project)")
    (project_wheel,) = wheelhouse.glob("dct_controller-*.whl")
    if "ros" in extras:
        build_source_only_wheels(wheelhouse)
    plat = [a for p in manylinux_platforms(glibc) for a in ("--platform", p)]
    abi = "cp" + python_version.replace(".", "")
    wanted = str(project_wheel) + (f"[{','.join(extras)}]" if extras else "")
    _pip(["download", "--quiet", "--only-binary=:all:", *plat, "--python-version", python_version,
          "--implementation", "cp", "--abi", abi, "--find-links", str(wheelhouse), "-d", str(wheelhouse), wanted],
         f"pip download (dependencies for CPython {python_version}, {MACHINE}, glibc {glibc})")


#: Dependencies of the ROS 2 wheels published only as source, pure Python: rosidl-adapter needs
#: empy. `pip download --platform` takes wheels only, and without one pip backtracks until it gives
#: up ("resolution exceeded maximum depth"); their wheels are built here, for any target.
ROS_SOURCE_ONLY = ("empy==4.2.1",)


def build_source_only_wheels(wheelhouse: Path) -> None:
    """Pure-Python wheels of ROS_SOURCE_ONLY into `wheelhouse` (found there by --find-links)."""
    with tempfile.TemporaryDirectory(prefix="dct-sdist-") as tmp:
        _pip(["download", "--quiet", "--no-deps", "--no-binary=:all:", "-d", tmp, *ROS_SOURCE_ONLY],
             "pip download (the ROS 2 wheels' source-only dependencies)")
        _pip(["wheel", "--quiet", "--no-deps", "-w", str(wheelhouse), *map(str, sorted(Path(tmp).iterdir()))],
             "pip wheel (the ROS 2 wheels' source-only dependencies)")


def ros_extra_requirements(root: Path | None = None) -> list[tuple[str, str]]:
    """(name, pinned version) of each package of the project's `ros` extra (pyproject.toml)."""
    import tomllib

    try:
        with open((root or project_root()) / "pyproject.toml", "rb") as f:
            extra = tomllib.load(f)["project"]["optional-dependencies"]["ros"]
    except (OSError, KeyError, BundleError, tomllib.TOMLDecodeError) as exc:
        raise BundleError(f"cannot read the project's ros extra from pyproject.toml ({exc})") from None
    out = []
    for req in extra:
        name, sep, version = req.partition("==")
        if not sep:
            raise BundleError(f"pyproject.toml: the ros extra's {req!r} is not pinned (name==version)")
        out.append((name.strip(), version.strip()))
    return out


def _wheel_name(name: str, version: str) -> str:
    """The start of a wheel file's name for a distribution (PEP 427: runs of -_. become _)."""
    import re

    return re.sub(r"[-_.]+", "_", name).lower() + f"-{version}-"


def check_wheelhouse(wheelhouse: Path, ros_required: list[tuple[str, str]] = ()) -> list[str]:
    """Refuse a CUDA torch, and a wheelhouse without the `ros_required` wheels; returns the wheel names."""
    names = sorted(p.name for p in wheelhouse.iterdir())
    not_wheels = [n for n in names if not n.endswith(".whl")]
    if not_wheels:
        raise BundleError(f"wheelhouse holds files that are not wheels: {not_wheels[:5]}")
    if not any(n.startswith("dct_controller-") for n in names):
        raise BundleError("wheelhouse has no dct_controller wheel")
    cuda = [n for n in names if n.lower().startswith(CUDA_WHEEL_PREFIXES)]
    torch = [n for n in names if n.startswith("torch-")]
    if cuda or any("+cpu" not in n for n in torch):
        raise BundleError(f"the wheelhouse got a CUDA torch ({torch}, {len(cuda)} nvidia/triton wheels): "
                          "pip must find torch==2.13.0+cpu (docs/deploy.md: pip's find-links holds it; or "
                          "PIP_FIND_LINKS=<folder with the CPU wheel>)")
    lower = [n.lower() for n in names]
    missing = [f"{n}=={v}" for n, v in ros_required if not any(w.startswith(_wheel_name(n, v)) for w in lower)]
    if missing:
        raise BundleError(f"--ros wheels: the wheelhouse lacks {', '.join(missing)} (the project's ros extra): "
                          "pip found no such wheel for the target; build with --ros system or --ros none")
    return names


# ----------------------------------------------------------------------------- the bundle


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_manifest(folder: Path, info: dict) -> dict:
    files = []
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != "MANIFEST.json":
            files.append({"path": p.relative_to(folder).as_posix(), "sha256": sha256_file(p), "size": p.stat().st_size})
    manifest = {**info, "files": files}
    (folder / "MANIFEST.json").write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return manifest


def _project_version() -> str:
    try:
        return metadata.version(PROJECT)
    except metadata.PackageNotFoundError:
        return "0.0.0"


def _config_text(config_path: Path | None, model_name: str, custom_model: bool) -> str:
    """The config as given (byte for byte); a config naming its own distance net points at the
    bundled copy instead, an absolute path under @TARGET@ that install.sh fills in."""
    path = Path(str(resources.files("runtime") / "config" / "default.yaml")) if config_path is None else config_path
    text = path.read_text(encoding="utf-8")
    if not custom_model:
        return text
    import yaml

    data = yaml.safe_load(text)
    data["planner"]["distance_net_path"] = f"{templates.TARGET_PLACEHOLDER}/robot/models/{model_name}"
    return "# Written by dct deploy bundle from " + str(path) + " (distance_net_path -> the bundled model)\n" + \
        yaml.safe_dump(data, sort_keys=False)


def build_bundle(out: str | Path, inputs: BundleInputs = BundleInputs(), *, force: bool = False,
                 source: Path | None = None, python_version: str = DEFAULT_PYTHON, glibc: str = DEFAULT_GLIBC,
                 can_interface: str = "socketcan", can_channel: str = "can0", service_cpus: str | None = None,
                 watchdog_s: float = 2.0, compresslevel: int = 1, ros: str = DEFAULT_ROS,
                 wheelhouse_builder: Callable[[Path, Path], None] | None = None,
                 echo: Callable[[str], None] = lambda s: None) -> BundleResult:
    """Build the bundle at `out` (see the module docstring). `wheelhouse_builder(source, wheelhouse)`
    replaces the pip steps (tests use a tiny fake wheelhouse); with ros="wheels" it must put the
    project's ros extra there too."""
    times: dict[str, float] = {}
    t = time.perf_counter()
    out = check_out_path(Path(out), force)
    _check_options(compresslevel, watchdog_s, glibc)
    source = project_root() if source is None and wheelhouse_builder is None else source
    files = validate_inputs(inputs)
    robot, config = files.robot, files.config
    _check_ros(ros, config, python_version)
    ros_required = ros_extra_requirements(source) if ros == "wheels" else []
    rt = config.realtime
    cpus = _service_cpus(rt, service_cpus)
    times["validate_s"] = time.perf_counter() - t

    version = _project_version()
    folder_name = f"dct-bundle-{version}"
    notes = []
    with tempfile.TemporaryDirectory(prefix="dct-bundle-") as tmp:
        folder = Path(tmp) / folder_name
        wheelhouse = folder / "wheelhouse"
        wheelhouse.mkdir(parents=True)
        t = time.perf_counter()
        wheels = _fill_wheelhouse(wheelhouse, source, wheelhouse_builder, python_version, glibc, echo, ros_required)
        times["wheelhouse_s"] = time.perf_counter() - t
        echo(f"wheelhouse: {len(wheels)} wheels, {sum(p.stat().st_size for p in wheelhouse.iterdir()) / 1e6:.0f} MB "
             f"in {times['wheelhouse_s']:.1f} s")

        t = time.perf_counter()
        notes += _write_robot_files(folder / "robot", inputs, robot, config)
        values = dict(MACHINE=MACHINE, PYTHON=python_version, GLIBC=glibc, PROJECT=PROJECT, VERSION=version,
                      ROBOT=robot.name, UNIT=templates.UNIT_NAME, PRIORITY=rt.fifo_priority, CPUS=cpus,
                      WATCHDOG_S=f"{watchdog_s:g}", CAN_INTERFACE=can_interface, CAN_CHANNEL=can_channel,
                      ARCHIVE=out.name, FOLDER=folder_name, **templates.ros_values(ros, ROS_DISTRO),
                      NOTES="".join(f"\nNote: {n}\n" for n in notes))
        _write_scripts(folder, values, ros)
        manifest = write_manifest(folder, {
            "format": 2, "robot": robot.name,
            "project": {"name": PROJECT, "version": version},
            "target": {"machine": MACHINE, "python": python_version, "glibc": glibc},
            "built": {"utc": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
                      "host": platform.node(), "python": platform.python_version()},
            "ros": _ros_manifest(ros, ros_required), "wheels": wheels, "notes": notes})
        times["files_s"] = time.perf_counter() - t

        t = time.perf_counter()
        echo(f"archive: writing {out} (gzip level {compresslevel})")
        with atomic_file(out) as raw:
            with tarfile.open(fileobj=raw, mode="w:gz", compresslevel=compresslevel) as tar:
                tar.add(folder, arcname=folder_name)
        times["archive_s"] = time.perf_counter() - t
    return BundleResult(path=out, folder=folder_name, files=len(manifest["files"]) + 1, size_bytes=out.stat().st_size,
                        wheels=len(wheels), seconds=times, notes=notes)


def _check_options(compresslevel: int, watchdog_s: float, glibc: str) -> None:
    """Refuse bad options before the long work."""
    if not 0 <= compresslevel <= 9:
        raise BundleError(f"compresslevel must be 0-9, got {compresslevel}")
    if not 0.5 <= watchdog_s <= 600:
        raise BundleError(f"watchdog_s must be in [0.5, 600], got {watchdog_s}")
    manylinux_platforms(glibc)  # a bad --glibc fails here, before the long work


def _check_ros(ros: str, config, python_version: str) -> None:
    """The ROS 2 mode against the config and the target's CPython, before the long work."""
    if ros not in ROS_MODES:
        raise BundleError(f"--ros {ros!r}: give one of {', '.join(ROS_MODES)}")
    want_py = ROS_DISTRO_PYTHON[ROS_DISTRO]
    if ros == "system" and python_version != want_py:
        raise BundleError(f"--ros system: ROS 2 {ROS_DISTRO}'s rclpy is built for CPython {want_py}, and the venv "
                          f"must run the same to import it; pass --python-version {want_py} (got {python_version})")
    if ros == "none" and config.ros.middleware == "rclpy":
        raise BundleError("--ros none carries no rclpy, but the config asks for ros.middleware: rclpy; use "
                          "--ros wheels or --ros system, or set ros.middleware: auto or cyclonedds")
    if config.ros.security is not None and ros != "system":
        raise BundleError(f"the config sets ros.security (SROS2), which needs a ROS 2 built with DDS Security: "
                          f"--ros {ros} has none (the ROS 2 wheels have no DDS Security); use --ros system")


def _ros_manifest(ros: str, ros_required: list[tuple[str, str]]) -> dict:
    """MANIFEST.json's `ros`: what dct preflight checks (ros:install)."""
    out: dict = {"mode": ros, "distro": ROS_DISTRO}
    if ros == "wheels":
        out["wheels"] = [f"{n}=={v}" for n, v in ros_required]
    elif ros == "system":
        out["setup"] = f"/opt/ros/{ROS_DISTRO}/setup.bash"
    return out


def _fill_wheelhouse(wheelhouse: Path, source: Path | None, builder: Callable[[Path, Path], None] | None,
                     python_version: str, glibc: str, echo: Callable[[str], None],
                     ros_required: list[tuple[str, str]]) -> list[str]:
    """The wheels, by `builder` when given (tests), else by pip; checked (no CUDA torch; the ROS 2
    wheels when they are to be carried)."""
    echo(f"wheelhouse: building ({'custom' if builder else f'pip, CPython {python_version} {MACHINE}'}"
         f"{', with the ROS 2 wheels' if ros_required else ''})")
    if builder is not None:
        builder(source, wheelhouse)
    else:
        build_wheelhouse(source, wheelhouse, python_version=python_version, glibc=glibc,
                         extras=("ros",) if ros_required else ())
    return check_wheelhouse(wheelhouse, ros_required)


def _service_cpus(rt, service_cpus: str | None) -> str:
    """The unit's CPUAffinity: the given CPUs, else 0 and 1 plus the config's realtime.cpus,
    which must lie within them."""
    cpus = service_cpus or " ".join(str(c) for c in sorted(set(rt.cpus or ()) | {0, 1}))
    try:
        cpu_set = {int(c) for c in cpus.replace(",", " ").split()}
    except ValueError:
        raise BundleError(f"service CPUs {cpus!r}: give CPU numbers like '0 1'") from None
    if rt.cpus and not set(rt.cpus) <= cpu_set:
        raise BundleError(f"config realtime.cpus {list(rt.cpus)} is not within the service's CPUs {sorted(cpu_set)}")
    return cpus


def _write_robot_files(rdir: Path, inputs: BundleInputs, robot, config) -> list[str]:
    """robot.yaml, calibration.yaml, config.yaml and the distance net into `rdir`; returns the
    notes for the user (a nominal calibration, the shipped net)."""
    from models.distance_net import shipped_artifact_path

    notes = []
    (rdir / "models").mkdir(parents=True)
    robot_src = inputs.robot or Path(str(resources.files("calibration") / "robots" / "limo.yaml"))
    shutil.copyfile(robot_src, rdir / "robot.yaml")
    if inputs.calibration is not None:
        shutil.copyfile(inputs.calibration, rdir / "calibration.yaml")
    else:
        (rdir / "calibration.yaml").write_text(nominal_calibration_yaml(robot), encoding="utf-8")
        notes.append("calibration.yaml is NOMINAL (from the robot description): calibrate the robot's camera "
                     "(dct calibrate) and replace it; dct preflight warns until then")
    model_src = Path(config.planner.distance_net_path) if config.planner.distance_net_path else shipped_artifact_path()
    shutil.copyfile(model_src, rdir / "models" / model_src.name)
    custom_model = config.planner.distance_net_path is not None
    (rdir / "config.yaml").write_text(_config_text(inputs.config, model_src.name, custom_model), encoding="utf-8")
    if not custom_model:
        notes.append(f"config.yaml uses the distance net shipped in the wheel; robot/models/{model_src.name} is "
                     "the same file (compare the sha256 in MANIFEST.json)")
    return notes


def _write_scripts(folder: Path, values: dict, ros: str) -> None:
    """The systemd unit, install.sh and README.txt, rendered with `values`; bin/dct-env for --ros system."""
    if ros == "system":
        (folder / "bin").mkdir()
        env = folder / "bin" / "dct-env"
        env.write_text(templates.render(templates.ENV_SH, **values), encoding="utf-8")
        env.chmod(0o755)
    (folder / "systemd").mkdir()
    (folder / "systemd" / templates.UNIT_NAME).write_text(templates.render(templates.UNIT, **values), encoding="utf-8")
    install = folder / "install.sh"
    install.write_text(templates.render(templates.INSTALL_SH, **values), encoding="utf-8")
    install.chmod(0o755)
    (folder / "README.txt").write_text(templates.render(templates.README, **values), encoding="utf-8")


__all__ = ["BundleError", "BundleInputs", "BundleResult", "build_bundle", "build_wheelhouse", "check_wheelhouse",
           "manylinux_platforms", "nominal_calibration_yaml", "project_root", "ros_extra_requirements",
           "write_manifest", "ROS_MODES", "DEFAULT_ROS"]
