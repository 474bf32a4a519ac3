# The README's two set-up commands: `make demo` and `make test`. Both install
# missing Debian packages first (nothing when all are present), then build.
PYTHON ?= /usr/bin/python3
BUILD ?= build
JOBS ?= $(shell nproc)
PROFILE ?= smoke

PACKAGES := build-essential cmake libtorch-dev libopenblas0-openmp libgloo-dev libeigen3-dev \
            libyaml-cpp-dev libhdf5-dev libfmt-dev catch2 libcli11-dev \
            python3-matplotlib python3-h5py python3-numpy

.PHONY: all deps build test demo clean

all: build

deps:
	@missing=""; for p in $(PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing missing packages:$$missing"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	else echo "all packages present"; fi

# ccache, when the machine has it, shares objects across clones and worktrees: paths
# under the checkout are hashed relative to it and the checkout's own path is
# compiled into one file only (src/core/source_dir.cpp).
CCACHE := $(shell command -v ccache 2>/dev/null)
ifneq ($(CCACHE),)
LAUNCHER := -DCMAKE_CXX_COMPILER_LAUNCHER=$(CCACHE)
export CCACHE_BASEDIR := $(CURDIR)
export CCACHE_SLOPPINESS := pch_defines,time_macros,include_file_mtime,include_file_ctime
endif

build: deps
	@cmake -S . -B $(BUILD) -DCMAKE_BUILD_TYPE=Release -DPYTHON=$(PYTHON) $(LAUNCHER) > $(BUILD).cmake.log 2>&1 || (cat $(BUILD).cmake.log; exit 1)
	cmake --build $(BUILD) -j$(JOBS)

test: build
	cd $(BUILD) && OMP_NUM_THREADS=1 ctest --output-on-failure -j$(JOBS) --timeout 900

demo: build
	PYTHON=$(PYTHON) BUILD=$(BUILD) PROFILE=$(PROFILE) bash tools/demo.sh

clean:
	rm -rf $(BUILD)
