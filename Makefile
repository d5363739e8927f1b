# One-command install and run. `make demo` / `make test` install everything first (idempotent).
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.stamps
MSG_PKG := msg_schemas/lq_msgs
# Keep DDS discovery on this machine (a user on a robot network may override it).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export MUJOCO_GL ?= egl

LEROBOT_VENV := .venv-lerobot
# LeRobot 0.6 (SmolVLA, pi0, pi0.5 as published) needs Python >= 3.12 (pyenv's, or PYTHON312=...).
LEROBOT06_VENV := .venv-lerobot06
# LeRobot 0.6's simulator (hf-libero 0.1.4, MuJoCo 3.8.1), for benchmarks/physics_gap.py only.
HFLIBERO_VENV := .venv-hflibero
PYTHON312 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.12*/bin/python) $(shell command -v python3.12))

.PHONY: setup setup-all setup-lerobot setup-lerobot06 setup-hflibero test test-fast demo lint clean bytecode

setup: $(STAMP)/package

# LeRobot's own venv: LeRobot checkpoints are served from it (--policy lerobot; docs/guide/lerobot.md).
setup-lerobot: $(LEROBOT_VENV)/.stamps/wheels

# pip compiles the bytecode of what it installs on one core; the venvs (about 51,000 files) are installed without
# it and compiled on every core. pip, too, skips files that do not compile.
COMPILE_VENV = -c "import compileall, sysconfig; [compileall.compile_dir(sysconfig.get_path(k), quiet=2, workers=0) \
  for k in sorted({'purelib', 'platlib'})]"

$(LEROBOT_VENV)/.stamps/wheels: requirements-lerobot.lock
	@test -x $(LEROBOT_VENV)/bin/python || $(PYTHON) -m venv $(LEROBOT_VENV)
	$(LEROBOT_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --no-compile \
	  -r requirements-lerobot.lock
	$(LEROBOT_VENV)/bin/python $(COMPILE_VENV)
	@mkdir -p $(LEROBOT_VENV)/.stamps && touch $@

# LeRobot 0.6's venv on Python 3.12 (docs/guide/lerobot.md, "LeRobot 0.6"); --policy-arg python= selects it.
setup-lerobot06: $(LEROBOT06_VENV)/.stamps/wheels

$(LEROBOT06_VENV)/.stamps/wheels: requirements-lerobot06.lock
	@test -n "$(PYTHON312)" || { echo "setup-lerobot06: no Python 3.12 (pyenv's or python3.12); set PYTHON312=PATH"; false; }
	@test -x $(LEROBOT06_VENV)/bin/python || $(PYTHON312) -m venv $(LEROBOT06_VENV)
	$(LEROBOT06_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --no-compile \
	  -r requirements-lerobot06.lock
	$(LEROBOT06_VENV)/bin/python $(COMPILE_VENV)
	@mkdir -p $(LEROBOT06_VENV)/.stamps && touch $@

# hf-libero on MuJoCo 3 beside this stack's LIBERO on MuJoCo 2.3.7 (docs/guide/lerobot.md, "Physics"). Not part
# of setup-all: only benchmarks/physics_gap.py uses it.
setup-hflibero: $(HFLIBERO_VENV)/.stamps/wheels

$(HFLIBERO_VENV)/.stamps/wheels: requirements-hflibero.lock
	@test -n "$(PYTHON312)" || { echo "setup-hflibero: no Python 3.12 (pyenv's or python3.12); set PYTHON312=PATH"; false; }
	@test -x $(HFLIBERO_VENV)/bin/python || $(PYTHON312) -m venv $(HFLIBERO_VENV)
	$(HFLIBERO_VENV)/bin/python -m pip install --quiet --disable-pip-version-check --no-deps -r requirements-hflibero.lock
	@mkdir -p $(HFLIBERO_VENV)/.stamps && touch $@

$(STAMP)/wheels: requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check --no-compile -r requirements.lock
	$(PY) $(COMPILE_VENV)
	@mkdir -p $(STAMP) && touch $@

# Custom messages: rclpy classes generated from msg_schemas (the same files rosbags reads).
$(STAMP)/msgs: $(STAMP)/wheels $(MSG_PKG)/CMakeLists.txt $(MSG_PKG)/package.xml $(wildcard $(MSG_PKG)/msg/*.msg) \
  $(wildcard $(MSG_PKG)/srv/*.srv)
	rm -rf build/lq_msgs && mkdir -p build
	source $(VENV)/bin/activate && export AMENT_PREFIX_PATH=$$VIRTUAL_ENV && \
	cmake -S $(MSG_PKG) -B build/lq_msgs -G Ninja -DCMAKE_PREFIX_PATH=$$VIRTUAL_ENV \
	  -DCMAKE_INSTALL_PREFIX=$$VIRTUAL_ENV -DPython3_EXECUTABLE=$$VIRTUAL_ENV/bin/python \
	  -DBUILD_TESTING=OFF > build/lq_msgs.log 2>&1 || (cat build/lq_msgs.log; false)
	source $(VENV)/bin/activate && cmake --build build/lq_msgs >> build/lq_msgs.log 2>&1 && \
	  cmake --install build/lq_msgs >> build/lq_msgs.log 2>&1 || (cat build/lq_msgs.log; false)
	@touch $@

$(STAMP)/package: $(STAMP)/msgs setup.py setup.cfg package.xml
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	@touch $@

# The package's bytecode, as pip writes it for an installed wheel (this is an editable install): every node
# process imports these modules, and a Python that writes no caches (PYTHONDONTWRITEBYTECODE=1, common in
# containers) would otherwise compile them again in each. Up-to-date files are skipped.
bytecode: setup
	$(PY) -m compileall -q lq_ros nodes

# The three venvs install side by side: each pip runs on one core and waits on the disk much of the time.
setup-all:
	$(MAKE) -j3 setup setup-lerobot setup-lerobot06

# The suite in two parts: most tests on parallel workers (a module's tests stay on one worker, so the fixtures it
# shares start once), then the tests marked `serial` one at a time (a private Ray, a look at the machine's /dev/shm
# files). Both parts always run.
TEST_WORKERS ?= 2
test: setup-all
	$(MAKE) bytecode
	status=0; \
	$(PY) -m pytest -q -rfE --durations=25 -n $(TEST_WORKERS) --dist loadfile -m "not serial" || status=1; \
	$(PY) -m pytest -q -rfE --durations=10 -m serial || status=1; \
	exit $$status

test-fast: setup-all
	$(MAKE) bytecode
	$(PY) -m pytest -q -m "not slow"

demo: setup bytecode
	$(VENV)/bin/lq demo --out bags/demo

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf build $(VENV) $(LEROBOT_VENV) $(LEROBOT06_VENV) $(HFLIBERO_VENV) bags/demo
