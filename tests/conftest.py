import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

# Before any test module imports dolfinx or petsc4py: the wheel's MPI and PETSc libraries
# are found only once dolfinx_solver is imported, so a test file run alone needs this.
import dolfinx_solver  # noqa: E402, F401
