# Two entry points (README): `make demo` and `make test`. Both create .venv, install the
# pinned dependencies and the system packages for offscreen rendering, then run their job.
# Idempotent: a second run only re-checks the system packages and the install stamp.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.stamp-install
# Mesa for MuJoCo's offscreen rendering; chromium (and a font for it) for the test that opens
# `dct report latency`'s HTML in a real headless browser; node and npm for the test that reads a
# recording with Foxglove's own JavaScript MCAP and ROS 2 readers.
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 chromium fonts-dejavu-core nodejs
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: demo test install sysdeps clean

demo: install
	@mkdir -p out
	$(VENV)/bin/dct hil run case1 --json out/case1.json

# Two workers: the fast suite in about 6 minutes on 2 cores (docs/testing.md).
test: install
	$(VENV)/bin/python -m pytest -q -n 2

install: sysdeps $(STAMP)

$(STAMP): pyproject.toml tests/interop/js/package-lock.json
	@$(PY) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python 3.11+ is required")'
	test -x $(VENV)/bin/python || $(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	# torch first and pinned: an unpinned torch pulls several GB of CUDA packages.
	$(VENV)/bin/python -m pip install --quiet torch==2.13.0
	$(VENV)/bin/python -m pip install --quiet -e '.[test,bench,ros,eval]'
	# Foxglove's JS readers (pinned in tests/interop/js/package-lock.json) for the recording interop test.
	npm ci --prefix tests/interop/js --no-audit --no-fund --silent
	touch $@

# The APT_PACKAGES above, venv support and npm (Debian's package, unless a node install already has it);
# installed only when missing.
sysdeps:
	@missing=""; \
	for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	$(PY) -c 'import ensurepip, venv' >/dev/null 2>&1 || missing="$$missing python3-venv"; \
	command -v npm >/dev/null 2>&1 || missing="$$missing npm"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing; \
	fi

clean:
	rm -rf $(VENV) out
