"""The bundle's install script, systemd unit and README, as text templates.

Three kinds of placeholder:
- `@@NAME@@` is filled when the bundle is built (`render`): version, Python, robot name, CPUs,
  how ROS 2 comes (`ros_values`);
- `@TARGET@` is left in the unit (and in a config that names a bundled distance net, and in
  bin/dct-env) and filled by install.sh with the install folder, which is only known on the robot;
- `@ROS_SETUP@` (bin/dct-env, --ros system only): the robot's ROS 2 setup script, filled by
  install.sh (ROS_SETUP=, else /opt/ros/<distro>/setup.bash).
"""
from __future__ import annotations

import re

UNIT_NAME = "dct-controller.service"
#: Files of the bundle in which install.sh replaces @TARGET@ with the install folder.
TARGET_PLACEHOLDER = "@TARGET@"

INSTALL_SH = r"""#!/usr/bin/env bash
# Install the DCT controller from this bundle, offline:   ./install.sh TARGET [--force]
#
# 1. checks this computer (@@MACHINE@@, CPython @@PYTHON@@) and every file of the bundle against
#    MANIFEST.json (sha256 and size; a changed, missing or extra file stops the install);
# 2. python3 -m venv TARGET/venv, then pip install --no-index --find-links wheelhouse: nothing is
#    downloaded, pip's own configuration is ignored (PIP_CONFIG_FILE=/dev/null, --isolated);
# 3. copies the robot's files to TARGET/robot and the systemd unit to TARGET/systemd (with
#    TARGET filled in), makes TARGET/logs, and runs TARGET/venv/bin/dct --help.
# --force replaces an existing TARGET/venv and TARGET/robot. PYTHON=/path/to/python@@PYTHON@@ picks
# the interpreter (default: python3).
# ROS 2 (--ros @@ROS_MODE@@): @@ROS_NOTE@@
set -euo pipefail

usage() { echo "usage: $0 TARGET [--force]   (install the DCT controller into the folder TARGET)" >&2; exit 2; }
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
TARGET=""
FORCE=0
for arg in "$@"; do
  case "$arg" in
    --force) FORCE=1 ;;
    -h|--help) usage ;;
    -*) echo "install.sh: unknown option $arg" >&2; usage ;;
    *) [ -z "$TARGET" ] || { echo "install.sh: give one TARGET folder, got '$TARGET' and '$arg'" >&2; exit 2; }
       TARGET="$arg" ;;
  esac
done
[ -n "$TARGET" ] || usage
PY="${PYTHON:-python3}"
command -v "$PY" >/dev/null 2>&1 || { echo "install.sh: $PY not found; install CPython @@PYTHON@@ (with venv) or set PYTHON=" >&2; exit 1; }

# -- 1. this computer and the bundle's files
"$PY" - "$HERE" <<'PYEOF'
import hashlib, json, os, platform, sys
here = sys.argv[1]
def fail(msg):
    print("install.sh: " + msg, file=sys.stderr)
    sys.exit(1)
try:
    with open(os.path.join(here, "MANIFEST.json"), encoding="utf-8") as f:
        m = json.load(f)
    files = {e["path"]: e for e in m["files"]}
    target = m["target"]
except (OSError, ValueError, KeyError, TypeError) as exc:
    fail(f"MANIFEST.json is missing or unreadable ({exc}); the bundle is incomplete")
if platform.machine() != target["machine"]:
    fail(f"this bundle is for {target['machine']}, this computer is {platform.machine()}")
have = "%d.%d" % sys.version_info[:2]
if sys.implementation.name != "cpython" or have != target["python"]:
    fail(f"the wheelhouse is for CPython {target['python']}, {sys.executable} is "
         f"{sys.implementation.name} {have}; set PYTHON=/path/to/python{target['python']}")
bad = []
for path, e in sorted(files.items()):
    p = os.path.join(here, path)
    if not os.path.isfile(p):
        bad.append(f"{path}: missing")
        continue
    if os.path.getsize(p) != e["size"]:
        bad.append(f"{path}: size {os.path.getsize(p)}, manifest says {e['size']}")
        continue
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    if h.hexdigest() != e["sha256"]:
        bad.append(f"{path}: sha256 differs from the manifest")
for root, _dirs, names in os.walk(here):
    for n in names:
        rel = os.path.relpath(os.path.join(root, n), here).replace(os.sep, "/")
        if rel != "MANIFEST.json" and rel not in files:
            bad.append(f"{rel}: not in the manifest")
if bad:
    more = f" (and {len(bad) - 5} more)" if len(bad) > 5 else ""
    fail("the bundle does not match its MANIFEST.json, refusing to install: " + "; ".join(bad[:5]) + more)
print(f"install.sh: {len(files)} files match MANIFEST.json ({m['project']['name']} {m['project']['version']}, "
      f"robot '{m['robot']}')")
PYEOF
ROS_MODE="@@ROS_MODE@@"
ROS_SETUP="${ROS_SETUP:-/opt/ros/@@ROS_DISTRO@@/setup.bash}"
if [ "$ROS_MODE" = system ]; then
  [ -f "$ROS_SETUP" ] || { echo "install.sh: this bundle uses the robot's ROS 2 @@ROS_DISTRO@@ (built with --ros system), but $ROS_SETUP does not exist: install ROS 2 @@ROS_DISTRO@@ (apt install ros-@@ROS_DISTRO@@-ros-base), set ROS_SETUP=/path/to/its/setup.bash, or use a bundle built with --ros wheels" >&2; exit 1; }
  case "$ROS_SETUP" in
    *[!A-Za-z0-9_./+-]*) echo "install.sh: ROS_SETUP '$ROS_SETUP': give a plain path (letters, digits, _ . / + -)" >&2; exit 2 ;;
  esac
  ROS_SETUP="$(cd "$(dirname "$ROS_SETUP")" && pwd)/$(basename "$ROS_SETUP")"
fi

# -- 2. the target folder and the venv
mkdir -p "$TARGET"
TARGET="$(cd "$TARGET" && pwd)"
case "$TARGET" in
  *[[:space:]%]*) echo "install.sh: the target folder '$TARGET' has a space or a %: systemd would split or expand it in the unit; choose another" >&2; exit 2 ;;
esac
for sub in venv robot; do
  if [ -e "$TARGET/$sub" ]; then
    if [ "$FORCE" = 1 ]; then rm -rf "${TARGET:?}/$sub"
    else echo "install.sh: $TARGET/$sub already exists; pass --force to replace it" >&2; exit 1; fi
  fi
done
echo "install.sh: creating $TARGET/venv"
"$PY" -m venv "$TARGET/venv" || { echo "install.sh: python3 -m venv failed (Debian/Ubuntu: apt install python3-venv)" >&2; exit 1; }
echo "install.sh: installing @@PROJECT@@@@EXTRAS@@ @@VERSION@@ from the wheelhouse (offline)"
PIP_CONFIG_FILE=/dev/null "$TARGET/venv/bin/python" -m pip --isolated --disable-pip-version-check install \
  --no-index --find-links "$HERE/wheelhouse" --no-cache-dir --quiet "@@PROJECT@@@@EXTRAS@@==@@VERSION@@"

# -- 3. the robot's files, the unit, the log folder
cp -R "$HERE/robot" "$TARGET/robot"
mkdir -p "$TARGET/systemd" "$TARGET/logs"
cp "$HERE/systemd/@@UNIT@@" "$TARGET/systemd/@@UNIT@@"
FILL=("$TARGET/systemd/@@UNIT@@" "$TARGET/robot/config.yaml")
DCT="$TARGET/venv/bin/dct"
if [ "$ROS_MODE" = system ]; then
  mkdir -p "$TARGET/bin"
  cp "$HERE/bin/dct-env" "$TARGET/bin/dct-env"
  FILL+=("$TARGET/bin/dct-env")
  DCT="$TARGET/bin/dct-env $TARGET/venv/bin/dct"
fi
"$PY" - "$TARGET" "$ROS_SETUP" "${FILL[@]}" <<'PYEOF'
import sys
target, ros_setup = sys.argv[1], sys.argv[2]
for path in sys.argv[3:]:
    with open(path, encoding="utf-8") as f:
        text = f.read()
    with open(path, "w", encoding="utf-8") as f:
        f.write(text.replace("@TARGET@", target).replace("@ROS_SETUP@", ros_setup))
PYEOF
"$TARGET/venv/bin/dct" --help >/dev/null
cp "$HERE/MANIFEST.json" "$TARGET/MANIFEST.json"
cat <<EOF
install.sh: installed into $TARGET
  controller:   $DCT
  ROS 2:        --ros @@ROS_MODE@@
  robot files:  $TARGET/robot/ (robot.yaml, calibration.yaml, config.yaml, models/)
  check:        $DCT preflight --robot $TARGET/robot/robot.yaml --calibration $TARGET/robot/calibration.yaml --config $TARGET/robot/config.yaml --log-dir $TARGET/logs --manifest $TARGET/MANIFEST.json
  service:      sudo cp $TARGET/systemd/@@UNIT@@ /etc/systemd/system/ && sudo systemctl daemon-reload && sudo systemctl enable --now @@UNIT@@
EOF
"""

UNIT = """# DCT controller for robot '@@ROBOT@@' (made by `dct deploy bundle`; install.sh fills in @TARGET@).
# Install: sudo cp @TARGET@/systemd/@@UNIT@@ /etc/systemd/system/ && sudo systemctl daemon-reload
#          && sudo systemctl enable --now @@UNIT@@
[Unit]
Description=DCT contact-tolerant navigation controller (robot @@ROBOT@@)
After=network-online.target time-sync.target
Wants=network-online.target time-sync.target
# A controller that keeps failing stops being restarted after 5 tries in 2 minutes.
StartLimitIntervalSec=120
StartLimitBurst=5

[Service]
# Type=notify + WatchdogSec: the controller sends READY=1 once its loop runs and WATCHDOG=1 from
# the loop thread (runtime.app.deploy.sd_notify); a loop that hangs for WatchdogSec is killed and
# restarted, as is a process that dies. The base stops the wheels by itself 500 ms after the
# last command either way. The restarted controller continues the odometry frame and the goal
# saved in logs/resume.json (--resume-file) when they are younger than a minute.
Type=notify
NotifyAccess=main
WatchdogSec=@@WATCHDOG_S@@
Restart=on-failure
RestartSec=2
WorkingDirectory=@TARGET@
Environment=PYTHONUNBUFFERED=1
# ROS 2 (--ros @@ROS_MODE@@): @@ROS_NOTE@@
# Every check that driving needs must pass before the controller starts (dct preflight).
ExecStartPre=@@EXEC_PREFIX@@@TARGET@/venv/bin/dct preflight --robot @TARGET@/robot/robot.yaml --calibration @TARGET@/robot/calibration.yaml --config @TARGET@/robot/config.yaml --can-interface @@CAN_INTERFACE@@ --can-channel @@CAN_CHANNEL@@ --log-dir @TARGET@/logs --manifest @TARGET@/MANIFEST.json --json @TARGET@/logs/preflight.json
ExecStart=@@EXEC_PREFIX@@@TARGET@/venv/bin/dct run --robot @TARGET@/robot/robot.yaml --calibration @TARGET@/robot/calibration.yaml --config @TARGET@/robot/config.yaml --resume-file @TARGET@/logs/resume.json
# The controller stops cleanly (zero commands to the base) on SIGINT, as on Ctrl-C.
KillSignal=SIGINT
TimeoutStopSec=5
# Real time: the loop thread asks for SCHED_FIFO priority @@PRIORITY@@ (config realtime:) and
# this allows it without root; the service's threads run on CPUs @@CPUS@@.
LimitRTPRIO=@@PRIORITY@@
LimitMEMLOCK=infinity
CPUAffinity=@@CPUS@@
# User=dct   # a dedicated user in the 'dialout' (serial) group; LimitRTPRIO covers SCHED_FIFO.

[Install]
WantedBy=multi-user.target
"""

README = """DCT controller bundle: @@PROJECT@@ @@VERSION@@ for robot '@@ROBOT@@'
Target: @@MACHINE@@ Linux, CPython @@PYTHON@@ (glibc @@GLIBC@@ or newer).
ROS 2 (--ros @@ROS_MODE@@): @@ROS_NOTE@@

  tar xzf @@ARCHIVE@@ && ./@@FOLDER@@/install.sh /opt/dct

installs offline into /opt/dct (venv/, robot/, systemd/, logs/). Contents:
  install.sh            checks this computer and MANIFEST.json, then installs (see its header)
  MANIFEST.json         sha256 and size of every file; the target; the robot
  wheelhouse/           the project's wheel and every dependency (torch is the CPU build)
  robot/                robot.yaml, calibration.yaml, config.yaml, models/ (the distance net)
  systemd/@@UNIT@@  the service (Type=notify, WatchdogSec, Restart=on-failure,
                        LimitRTPRIO, CPUAffinity; runs dct preflight before the controller)@@ENV_LINE@@
@@NOTES@@"""

ENV_SH = r"""#!/usr/bin/env bash
# The DCT controller's environment on a robot with its own ROS 2 @@ROS_DISTRO@@ (a bundle built with
# --ros system): sources ROS 2's setup script, then runs the command it is given, e.g.
#   @TARGET@/bin/dct-env @TARGET@/venv/bin/dct preflight ...
# The systemd unit runs dct through it. install.sh wrote the setup script's path below.
if [ "$#" -eq 0 ]; then echo "usage: $0 COMMAND [ARGS...]   (run COMMAND with ROS 2 @@ROS_DISTRO@@ sourced)" >&2; exit 2; fi
export DCT_ROS_SETUP="@ROS_SETUP@"
if [ ! -f "$DCT_ROS_SETUP" ]; then
  echo "dct-env: $DCT_ROS_SETUP does not exist: ROS 2 @@ROS_DISTRO@@ is not installed here" >&2; exit 1
fi
# ROS 2's setup scripts read unset variables: no `set -u` here.
source "$DCT_ROS_SETUP" || { echo "dct-env: sourcing $DCT_ROS_SETUP failed" >&2; exit 1; }
exec "$@"
"""


def ros_values(mode: str, distro: str) -> dict[str, str]:
    """The placeholders that depend on how the bundle brings ROS 2 (runtime.app.deploy.bundle)."""
    notes = {
        "wheels": f"the ROS 2 {distro} wheels (rclpy with Fast DDS and the message packages) go into the venv: "
                  "the robot needs no ROS 2 install",
        "system": f"the robot's ROS 2 {distro}: dct runs through TARGET/bin/dct-env, which sources "
                  f"/opt/ros/{distro}/setup.bash (or install.sh's ROS_SETUP=)",
        "none": "no rclpy: ROS 2 topics through cyclonedds (ros.middleware auto or cyclonedds)",
    }
    return {"ROS_MODE": mode, "ROS_DISTRO": distro, "ROS_NOTE": notes[mode],
            "EXTRAS": "[ros]" if mode == "wheels" else "",
            "EXEC_PREFIX": "@TARGET@/bin/dct-env " if mode == "system" else "",
            "ENV_LINE": "\n  bin/dct-env           sources the robot's ROS 2, then runs dct (the unit uses it)"
                        if mode == "system" else ""}


def render(template: str, **values: object) -> str:
    """Fill every @@NAME@@; a placeholder left without a value is a bug, so it raises."""
    def sub(m: re.Match) -> str:
        key = m.group(1)
        if key not in values:
            raise KeyError(f"template placeholder @@{key}@@ has no value")
        return str(values[key])

    return re.sub(r"@@([A-Z_]+)@@", sub, template)
