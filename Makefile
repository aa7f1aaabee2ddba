# The two set-up commands of the README:  make demo  and  make test.
# Each creates .venv if missing, installs the project (building lidarscan_msgs into it), then runs.
PYTHON ?= python3
VENV   := .venv
V      := $(abspath $(VENV))
PY     := $(V)/bin/python
STAMP  := $(VENV)/.installed

# Children must not inherit the ROS wheels' bootstrap guard of another interpreter.
unexport _ROS_WHEELS_BOOTSTRAP_COMPLETE

.PHONY: install demo test bench evidence msgs tf2msgs clean

install: $(STAMP)

$(STAMP): pyproject.toml setup.py $(wildcard converters/_kernels/*.c) msgs/CMakeLists.txt msgs/package.xml $(wildcard msgs/msg/*.msg)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,viz,fast,msgs-build,dask]'
	$(MAKE) msgs
	$(MAKE) tf2msgs
	$(PY) -m converters.warmup  # fill numba's cache: nodes start ready (bench/README.md)
	touch $(STAMP)

# Build the interface package into the venv with cmake + ninja (about 15 s). Into another
# environment (after its `pip install '.[msgs-build]'`): make msgs tf2msgs VENV=/path/to/env
msgs:
	rm -rf build/msgs
	mkdir -p build
	env -u LD_LIBRARY_PATH AMENT_PREFIX_PATH=$(V) CMAKE_PREFIX_PATH=$(V) \
	  cmake -S msgs -B build/msgs -G Ninja -DCMAKE_INSTALL_PREFIX=$(V) \
	  -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF -DPython3_EXECUTABLE=$(PY) >build/msgs.log 2>&1 \
	  || (cat build/msgs.log; exit 1)
	cmake --build build/msgs --target install >>build/msgs.log 2>&1 || (cat build/msgs.log; exit 1)

# tf2_msgs (TFMessage, for /tf and /tf_static) is not in the wheels: build third_party/tf2_msgs
# the same way, unless the environment already provides it.
tf2msgs:
	@$(PY) -c "import tf2_msgs.msg" 2>/dev/null && echo "tf2_msgs already available" || ( \
	  rm -rf build/tf2_msgs && mkdir -p build && \
	  env -u LD_LIBRARY_PATH AMENT_PREFIX_PATH=$(V) CMAKE_PREFIX_PATH=$(V) \
	  cmake -S third_party/tf2_msgs -B build/tf2_msgs -G Ninja -DCMAKE_INSTALL_PREFIX=$(V) \
	  -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF -DPython3_EXECUTABLE=$(PY) >build/tf2_msgs.log 2>&1 \
	  && cmake --build build/tf2_msgs --target install >>build/tf2_msgs.log 2>&1 \
	  || (cat build/tf2_msgs.log; exit 1) )

demo: install
	$(V)/bin/lidarscan demo

test: install
	$(PY) -m pytest -q tests

bench: install
	$(PY) bench/run_all.py

evidence: install
	$(PY) -m converters.edge.evidence

clean:
	rm -rf build $(VENV)
