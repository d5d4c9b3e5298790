# Two commands for a newcomer: `make demo` and `make test`. Both build .venv first.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
MPIRUN := $(VENV)/bin/mpirun
export OMP_NUM_THREADS := 1

# DOLFINx wheels need Python >= 3.12; the machine's default python3 may be older, and
# pyenv shims refuse versions that are not selected, so look at real interpreters first.
find_python = for p in $$(ls -d $$(pyenv root 2>/dev/null)/versions/3.12*/bin/python3 \
	$$(pyenv root 2>/dev/null)/versions/3.13*/bin/python3 2>/dev/null) \
	python3.12 python3.13 python3; do \
	if command -v $$p >/dev/null 2>&1 && $$p -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; \
	then echo $$p; break; fi; done

.PHONY: demo test test-serial test-mpi lint venv clean install-check new-meshes

venv: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@python=$$($(find_python)); \
	if [ -z "$$python" ]; then echo "error: no Python >= 3.12 found (DOLFINx needs it); install one, e.g. 'pyenv install 3.12'" >&2; exit 1; fi; \
	echo "using $$python ($$($$python --version))"; \
	[ -x $(PY) ] || $$python -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	@touch $@

demo: venv
	$(MPIRUN) -n 2 $(PY) -m hyper.demo

test: venv test-serial test-mpi

test-serial: venv
	$(PY) -m pytest -q

test-mpi: venv
	$(MPIRUN) -n 2 $(PY) -m pytest -q --with-mpi -m mpi -p no:cacheprovider

# The 19 meshes/M_S_side/ of geometry.NEW from the Visible Human surfaces (docs/meshing.md "A mesh from
# a surface"). The VHM frame's z axis points distally (its TA lies below its thigh), the VHF
# frame's proximally: the origin (tag 1) is the end toward +z for VHF and toward -z for VHM.
# --end-rule vertices: as the shipped ones were made (docs/convergence.md). Their own fibres
# (fibers.h5) are hyper mesh's Laplace fibres; the paper's Stokes fibres, unsmoothed, go
# beside them (fibers_stokes.h5, for --settings original), as for the 12 paper meshes.
SURFACES ?= ../shared/surfaces
NEW_MUSCLES := RectusFemoris:RF VastusLateralis:VL VastusMedialis:VM VastusIntermedius:VI GastrocnemiusMedial:GM
new-meshes: venv
	@for pair in $(NEW_MUSCLES); do for stl in $(SURFACES)/VH?_*_Muscle_$${pair%%:*}_smooth.stl; do \
	  base=$$(basename $$stl); subject=$${base%%_*}; rest=$${base#*_}; side=$${rest%%_*}; \
	  toward="0 0 1"; [ $$subject = VHM ] && toward="0 0 -1"; name=$${pair##*:}_$${subject}_$$side; \
	  $(PY) -m hyper.mesh $$stl --output meshes/$$name --origin-toward $$toward --force --end-rule vertices \
	    && $(PY) -m hyper.fibers --geometries $$name --method stokes --force --output results/fibers \
	    || exit 1; done; done

lint: venv
	$(VENV)/bin/ruff check src tests jobs

# A user's install: `pip install .` (not editable, dependencies from PyPI) into a fresh
# venv, then a run from an empty folder, so nothing of the checkout is within reach.
FRESH ?= /tmp/hyper-fresh-venv
install-check:
	@python=$$($(find_python)); rm -rf $(FRESH); $$python -m venv $(FRESH)
	$(FRESH)/bin/pip install -q .
	@empty=$$(mktemp -d); cd $$empty && OMP_NUM_THREADS=1 $(FRESH)/bin/hyper grow --geometry idealized \
	  --protocol weekly --quiet && test -s results/grow/idealized_weekly.h5 && \
	  echo "install-check: a fresh venv's hyper grew the idealized muscle in $$empty" && rm -rf $$empty $(FRESH)

clean:
	rm -rf $(VENV)
