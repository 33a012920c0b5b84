# knitfem: `make demo` runs the hanging 7×7 jersey, `make test` the test suite.
# Both set everything up first (Debian packages, .venv, editable install).

PYTHON  := /usr/bin/python3
VENV    := .venv
VPY     := $(VENV)/bin/python
APT     := python3-petsc4py python3-mpi4py python3-h5py python3-meshio \
           python3-scipy python3-matplotlib python3-pytest python3-pytest-xdist python3-venv \
           python3-setuptools python3-pip openmpi-bin cython3 python3-dev gcc \
           libopenblas-dev python3-sphinx furo python3-myst-parser
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_rmaps_base_oversubscribe := 1
MPIRUN  := mpirun -n 2
PYTEST  := $(VPY) -m pytest -p no:cacheprovider -q
OUT     ?= out/demo

.PHONY: setup apt demo test test-serial test-parallel docs clean

# Byte-compiled now, so that a run reads its modules' .pyc even where
# PYTHONDONTWRITEBYTECODE is set (40 ms of every process's start otherwise).
setup: apt $(VENV)/.installed
	@$(VPY) -m compileall -q knitfem solvers benchmarks >/dev/null

# Installs only what dpkg does not already have (seconds when all is there).
apt:
	@missing=$$(for p in $(APT); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null \
	  | grep -q "install ok installed" || echo $$p; done); \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:" $$missing; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	    apt-get install -y -qq --no-install-recommends $$missing; \
	fi

# The venv sees Debian's numpy/petsc4py; a .pth file points at Debian's
# real-scalar petsc4py when /usr/lib/petsc (from the -dev package) is absent.
# pip install -e . also compiles the yarn and contact kernels (Cython) in
# place. The IPC Toolkit (yarn contact) comes as a wheel, without its
# dependencies (they are Debian's: numpy, scipy), so that pip never replaces
# Debian's numpy.
IPCTK   := ipctk==1.6.1

$(VENV)/.installed: setup.py knitfem/yarn/_compiled.pyx knitfem/contact/_pairs.pyx Makefile
	test -x $(VPY) || $(PYTHON) -m venv --system-site-packages $(VENV)
	site=$$($(VPY) -c "import sysconfig; print(sysconfig.get_paths()['purelib'])"); \
	petsc=$$(ls -d /usr/lib/petscdir/petsc3.*/x86_64-linux-gnu-real/lib/python3/dist-packages | tail -n 1); \
	echo "$$petsc" > "$$site/debian-petsc4py.pth"
	$(VPY) -m pip install -q --no-deps --no-build-isolation -e .
	$(VPY) -m pip install -q --no-deps "$(IPCTK)"
	touch $@

demo: setup
	$(VENV)/bin/knitfem run -knit_scene hanging -knit_rows 7 -knit_cols 7 \
	  -knit_snapshots 0,0.4,1,2,3 -knit_animation hanging.gif -o $(OUT)

test: setup test-serial test-parallel

# The serial tests in two processes (pytest-xdist), a file each at a time, so
# that a file's module-scoped models are built once; the mpirun files run
# without it.
test-serial:
	timeout 900 $(PYTEST) -n 2 --dist loadfile tests

test-parallel:
	timeout 900 $(MPIRUN) $(PYTEST) tests/test_parallel.py tests/test_aij.py tests/test_mixed.py tests/test_mixed_sampling.py tests/test_contacts.py tests/test_sliding.py \
	  tests/test_frame.py tests/test_tube.py tests/test_shell.py tests/test_api.py tests/test_pattern.py \
	  tests/test_yarn_contact.py tests/test_lengths.py tests/test_conservation.py
	# the saddle tests count factorisation events: a process of their own
	timeout 300 $(MPIRUN) $(PYTEST) tests/test_saddle.py

# The documentation, warnings as errors; its options and results tables are
# written at build time (docs/_ext/knitfem_docs.py).
docs: setup
	$(VPY) -m sphinx -W --keep-going -q -b html docs docs/_build/html

clean:
	rm -rf $(VENV) out *.egg-info build knitfem/yarn/_compiled.c knitfem/yarn/*.so \
	  knitfem/contact/_pairs.c knitfem/contact/*.so \
	  docs/_build docs/_generated
