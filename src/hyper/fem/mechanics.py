"""Quasi-static muscle mechanics (MODEL.md §3): one problem object per mesh, built once.

Unknowns: displacement u (P2 vector) and pressure p (P1), Taylor–Hood on tetrahedra.
With an optional growth tensor Fg (F = Fe Fg, MODEL.md §4) the residual is

    ∫ P : ∇v dX + ∫ q (det Fe - 1) dX + Σ_{Γ1, Γ2} ∫ k (n·u)(n·v) |cof(F) N| dA = 0,

    P = det(Fg) Fe S(Fe) Fg⁻ᵀ   (consistent_stress=True)   or   Fe S(Fe)   (the original code),

with S the law of `hyper.model.material` and n = cof(F) N / |cof(F) N| the current normal
(Nanson). Without growth Fe = F and both choices are P = F S.

Rigid motions. The tendon springs act along the end normals only. On the curved ends
of the anatomical meshes they resist every rigid motion. On flat parallel ends
(idealized, cylinder) the translations across the axis and the rotation about it
cost nothing in the reference state, so the Jacobian there is singular. Which motions
are free is read off the 6×6 stiffness the springs give the rigid motions of the
reference body (`rigid_mode_stiffness`): its null space. Each free mode r is removed
by a Lagrange multiplier μ enforcing

    ∫ u·r dX = 0        (zero mean transverse displacement, zero mean axial rotation),

which adds μ·∫ r·v dX to the equilibrium equation. A deformation symmetric about the
axis through the body's centroid satisfies these exactly with μ = 0; in particular a
uniform transverse growth Fg of the cylinder gives u = (Fg - I)(X - X̄) and p = c1 + 2c2
to round-off. Point constraints were the alternative: they would need a vertex on
the axis (the cylinder mesh has none), and on Γ1, where the reaction force is
measured, their point load shifted it by 10 % on the idealized mesh. The multipliers
are global unknowns: the Newton matrix is [[J, B], [Bᵀ, 0]] in one AIJ matrix
(`_bordered_matrix`), factorised by MUMPS.

Linear solvers (``linear_solver``). "lu": MUMPS's exact factorisation, one solve per
Newton step. "iterative": GMRES, right-preconditioned by MUMPS's block low-rank (BLR)
factorisation at precision 1e-4 with compressed contribution blocks, to a relative
residual of 1e-10: the factors of the off-diagonal blocks of every front are stored as
low-rank products, which saves memory (the bench `solvers` measures how much) and the
Krylov iterations recover the accuracy. "amg" (experimental: no job offers it): GMRES
right-preconditioned by an upper Schur factorisation, GAMG on the displacement block
(the rigid-body near null space, block size 3), +(1/μ) M_p for the pressure, and for the
multipliers of free rigid motions the Schur complement taken with the same V-cycle
(`_preconditioner`, `_multiplier_schur`). Its Schur part is adequate (with an exact
displacement solve, 11-36 iterations a Newton step on TA), its AMG is not: one V-cycle
of GAMG on the P2 displacement block fails on the anatomical meshes; hypre is not in the
PETSc wheel. Measured in `python -m hyper.bench solvers --parts amg` (docs/performance.md).
"pmg" (`--linear-solver pmg`; `hyper.runs.fidelity` picks it for large meshes): the same
fieldsplit with a two-level P2 → P1 multigrid on the displacement block (`_coarse_gamg`):
Chebyshev/Jacobi on P2, GAMG on the Galerkin P1 operator. Its memory is about linear in
the mesh and its GMRES count nearly independent of it: in a growth solve on 2 ranks, 58.0
iterations a Newton step at 11k unknowns and 63.25 at 578k, where it takes 0.24 times LU's
time and 0.24 times its memory (`python -m hyper.bench solvers --parts levels`,
docs/performance.md). It holds one Newton matrix: the preconditioner is built from K
itself, and K is preallocated from DOLFINx's sparsity pattern (`_bordered_matrix`).
"""

from __future__ import annotations

import dataclasses
import weakref

import basix.ufl
import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from hyper.core.params import InputError
from hyper.fem.geometry import Geometry
from hyper.model import material as mat

DEFAULT_PETSC_OPTIONS = {
    "snes_type": "newtonls",
    "snes_linesearch_type": "basic",
    "snes_atol": 1e-8,
    "snes_rtol": 1e-8,
    # The solution vector mixes metres and pascals, so a step-size test says nothing.
    "snes_stol": 0.0,
    "snes_max_it": 25,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}

LINEAR_SOLVERS = ("lu", "iterative", "pmg")
# Built here, measured by `python -m hyper.bench solvers --parts amg`, offered by no job:
# its displacement block's AMG is too weak on the anatomical meshes (docs/performance.md).
EXPERIMENTAL_SOLVERS = ("amg",)
ITERATIVE_PETSC_OPTIONS = {
    "ksp_type": "gmres",
    "ksp_gmres_restart": 100,
    "ksp_pc_side": "right",
    "ksp_rtol": 1e-10,
    "ksp_atol": 0.0,
    "ksp_max_it": 200,
}
# MUMPS controls of the BLR preconditioner: ICNTL(35) = 2 BLR factors, ICNTL(37) = 1
# compressed contribution blocks; its dropping precision CNTL(7) is ``blr_precision``.
# On the idealized shape refined once (78k unknowns, 2 ranks) GMRES needs 42 iterations
# over 4 Newton steps at 1e-4, 290 at 1e-3, 635 at 1e-2 and fails at 1e-1; at 578k
# unknowns and 1e-4, 95 over 4, with 0.60x LU's memory (python -m hyper.bench solvers).
BLR_PRECISION = 1e-4

# "amg": GMRES right-preconditioned by a block upper-triangular Schur factorisation,
# smoothed-aggregation AMG (GAMG) on the displacement block, the pressure mass matrix
# scaled by the shear modulus for the Schur complement (`_preconditioner`). The
# sub-solvers' options are read at the first set-up (`_SUBSOLVERS`).
AMG_PETSC_OPTIONS = {
    "ksp_type": "gmres",
    "ksp_gmres_restart": 60,
    "ksp_pc_side": "right",
    "ksp_rtol": 1e-10,
    "ksp_atol": 0.0,
    "ksp_max_it": 600,
    "pc_type": "fieldsplit",
    "pc_fieldsplit_type": "schur",
    "pc_fieldsplit_schur_fact_type": "upper",
    "pc_fieldsplit_schur_precondition": "a11",
}
AMG_SUBSOLVER_OPTIONS = {
    "fieldsplit_u_ksp_type": "preonly",
    "fieldsplit_u_pc_type": "gamg",
    "fieldsplit_u_pc_gamg_threshold": 0.02,
    "fieldsplit_u_pc_gamg_aggressive_coarsening": 0,
    "fieldsplit_u_mg_levels_ksp_type": "chebyshev",
    "fieldsplit_u_mg_levels_pc_type": "jacobi",
    "fieldsplit_u_mg_levels_ksp_max_it": 3,
    "fieldsplit_p_ksp_type": "preonly",
    "fieldsplit_p_pc_type": "jacobi",
}
# The pressure split applies (μ M_p)⁻¹ by four Chebyshev/Jacobi steps on M_p (PCKSP on the
# Schur preconditioner matrix alone), a fixed linear map: one Jacobi step is a poor inverse
# on graded meshes. On TA_VHF_Left "pmg" needs 94.9 GMRES iterations a Newton step with it,
# 141.8 with one Jacobi step, and 24 s instead of 32 (jobs/solver_pmg.py TA_VHF_Left 0
# pmg-gamg pm=4; 8 steps: 88.5, no faster).
SCHUR_MASS_OPTIONS = {
    "fieldsplit_p_ksp_type": "preonly",
    "fieldsplit_p_pc_type": "ksp",
    "fieldsplit_p_ksp_ksp_type": "chebyshev",
    "fieldsplit_p_ksp_pc_type": "jacobi",
    "fieldsplit_p_ksp_ksp_max_it": 4,
    "fieldsplit_p_ksp_ksp_convergence_test": "skip",
}
# "pmg": the same fieldsplit with a two-level p-multigrid on the displacement block:
# Chebyshev/Jacobi on P2, the Galerkin P1 operator (interpolation from the P1 vector space
# on the same mesh) by GAMG with the rigid-body near null space of the P1 nodes
# (`_coarse_gamg`). A user's fieldsplit_u_mg_coarse_pc_type (lu, say) replaces the GAMG.
# GMRES restarts at 60 (AMG_PETSC_OPTIONS): at 4.4M unknowns a basis of 200 (36 MB a vector)
# took the growth solve on 1 rank past 23 GB; at 60 it peaked at 19.9 GB. On 2 ranks at
# 11k/78k/578k unknowns restart 60 takes 296/243/261 GMRES iterations against 290/238/253
# at 200 (python -m hyper.bench solvers --parts levels --pmg-option ksp_gmres_restart=60).
PMG_PETSC_OPTIONS = AMG_PETSC_OPTIONS
PMG_SUBSOLVER_OPTIONS = {
    "fieldsplit_u_ksp_type": "preonly",
    "fieldsplit_u_pc_type": "mg",
    "fieldsplit_u_pc_mg_levels": 2,
    "fieldsplit_u_pc_mg_galerkin": "both",
    "fieldsplit_u_mg_levels_ksp_type": "chebyshev",
    "fieldsplit_u_mg_levels_pc_type": "jacobi",
    "fieldsplit_u_mg_levels_ksp_max_it": 2,
    "fieldsplit_u_mg_coarse_ksp_type": "preonly",
    "fieldsplit_u_mg_coarse_pc_gamg_threshold": 0.02,
    "fieldsplit_u_mg_coarse_pc_gamg_aggressive_coarsening": 0,
    "fieldsplit_u_mg_coarse_mg_levels_ksp_type": "chebyshev",
    "fieldsplit_u_mg_coarse_mg_levels_pc_type": "jacobi",
    "fieldsplit_u_mg_coarse_mg_levels_ksp_max_it": 2,
    **SCHUR_MASS_OPTIONS,
}
COARSE_PC = "fieldsplit_u_mg_coarse_pc_type"
SUBSOLVER_OPTIONS = {"amg": AMG_SUBSOLVER_OPTIONS, "pmg": PMG_SUBSOLVER_OPTIONS}
# The shift ε M added to the displacement block of the preconditioner where the springs
# leave rigid motions free (its AMG hierarchy would be singular there), as a fraction of
# the shear modulus over the squared body size: the softest elastic motion of a body is
# about μ/L², so the shift perturbs it by ~1e-3 and GMRES corrects the few free ones.
AMG_SHIFT = 1e-3


def blr_controls(precision: float) -> dict:
    return {"mat_mumps_icntl_35": 2, "mat_mumps_icntl_37": 1, "mat_mumps_cntl_7": precision}


# Free rigid modes are those whose spring stiffness is below this fraction of the largest.
FREE_MODE_RATIO = 1e-8
_REASONS = {v: k for k, v in vars(PETSc.SNES.ConvergedReason).items() if isinstance(v, int)}
_KSP_REASONS = {v: k for k, v in vars(PETSc.KSP.ConvergedReason).items() if isinstance(v, int)}


def weak_callback(method):
    """``method`` (bound) called through a weak reference to its object. PETSc keeps the
    callbacks it is given where Python's collector cannot see them: a bound method handed
    to an SNES or KSP its object owns would keep the object, its mesh and their duplicated
    communicators alive for ever (MPICH has about 2000; a test suite ran out of them)."""
    ref = weakref.WeakMethod(method)

    def call(*args):
        return ref()(*args)

    return call


class SolverError(RuntimeError):
    """Newton did not converge; the problem holds the solution it had before the solve."""


@dataclasses.dataclass(frozen=True)
class RigidModes:
    """The rigid motions the end springs leave free, as UFL vectors r(X), and a summary."""

    modes: tuple
    description: str
    stiffness_ratio: float  # smallest/largest spring stiffness of the six rigid motions


class MechanicsProblem:
    """Taylor–Hood equilibrium with tendon springs, optional growth, SNES Newton + MUMPS.

    Forms and the solver are compiled once; between solves change ``alpha.value`` and
    the growth function in place. PETSc options: defaults < ``petsc_options`` < the
    options database under ``options_prefix`` (command line, PETSC_OPTIONS).
    """

    def __init__(
        self,
        geometry: Geometry,
        a0,
        material: mat.MaterialParams = mat.MaterialParams(),
        *,
        growth=None,
        consistent_stress: bool = True,
        petsc_options: dict | None = None,
        options_prefix: str = "mechanics_",
        linear_solver: str = "lu",
        blr_precision: float = BLR_PRECISION,
        normalize_fibres: bool = True,
    ):
        if linear_solver not in LINEAR_SOLVERS + EXPERIMENTAL_SOLVERS:
            raise ValueError(f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {linear_solver!r}")
        if not 0 < blr_precision < 1:
            raise ValueError(f"blr_precision must be in (0, 1), got {blr_precision!r}")
        self.linear_solver = linear_solver
        self.geometry = geometry
        self.material = material
        # A nodal fibre field is unit only at its nodes; the law needs unit fibres
        # wherever it is evaluated (near the idealized shape's axis the interpolant
        # is up to 4 % short). normalize_fibres=False: the field as it is (the original).
        if normalize_fibres:
            a0 = a0 / ufl.sqrt(ufl.dot(a0, a0))
        self.a0 = a0
        mesh = geometry.mesh
        self.comm = mesh.comm
        cell = mesh.basix_cell()
        element = basix.ufl.mixed_element(
            [basix.ufl.element("Lagrange", cell, 2, shape=(3,)), basix.ufl.element("Lagrange", cell, 1)]
        )
        self.W = fem.functionspace(mesh, element)
        self.w = fem.Function(self.W, name="w")
        self.u = self.w.sub(0)
        self.p = self.w.sub(1)
        self._p_dofs = np.asarray(self.W.sub(1).collapse()[1])
        self.alpha = fem.Constant(mesh, 0.0)

        u, p = ufl.split(self.w)
        v, q = ufl.TestFunctions(self.W)
        I = ufl.Identity(3)
        self.F = I + ufl.grad(u)
        if growth is None:
            self.Fe = self.F
            self.P = self.F * mat.second_piola(self.F, p, a0, self.alpha, material)
        else:
            self.Fe = self.F * ufl.inv(growth)
            S = mat.second_piola(self.Fe, p, a0, self.alpha, material)
            if consistent_stress:
                self.P = ufl.det(growth) * self.Fe * S * ufl.inv(growth).T
            else:
                self.P = self.Fe * S
        self.fibre_stretch = mat.fibre_stretch(self.F, a0)

        dx, ds = geometry.dx, geometry.ds
        N = ufl.FacetNormal(mesh)
        cofN = ufl.det(self.F) * ufl.inv(self.F).T * N
        area_ratio = ufl.sqrt(ufl.dot(cofN, cofN))
        n = cofN / area_ratio
        k = material.k_tendon
        residual = ufl.inner(self.P, ufl.grad(v)) * dx + q * (ufl.det(self.Fe) - 1.0) * dx
        for tag in geometry.ends:
            residual += k * ufl.dot(n, u) * ufl.dot(n, v) * area_ratio * ds(tag)
        self.residual = residual
        self.jacobian = ufl.derivative(residual, self.w)
        self._residual_form = fem.form(residual)
        self._jacobian_form = fem.form(self.jacobian)

        self.rigid = rigid_modes(geometry)
        self._build_system([fem.form(ufl.dot(r, v) * dx) for r in self.rigid.modes])
        self.multipliers = np.zeros(len(self.rigid.modes))
        self.krylov_iterations = 0  # over every solve (SNES's and `apply_inverse`'s); LU counts one a step

        self.snes = PETSc.SNES().create(self.comm)
        self.snes.setFunction(weak_callback(self._assemble_residual), self._F)
        self.snes.setOptionsPrefix(options_prefix)
        user = dict(petsc_options or {})
        # The sub-solvers of the fieldsplit read their options at its first set-up, long
        # after setFromOptions: they are kept here and put into the database for it.
        given = {k: v for k, v in user.items() if k.startswith(SUBSOLVER)}
        self._subsolver_options = ({**SUBSOLVER_OPTIONS[linear_solver], **given}
                                   if linear_solver in SUBSOLVER_OPTIONS else {})
        self._user_subsolver_options = tuple(k for k in user if k in self._subsolver_options)
        self._subsolvers_read = False
        preset = {"iterative": ITERATIVE_PETSC_OPTIONS, "amg": AMG_PETSC_OPTIONS,
                  "pmg": PMG_PETSC_OPTIONS}.get(linear_solver, {})
        read_now = {k: v for k, v in user.items() if k not in self._subsolver_options}
        _set_options(self.snes, options_prefix, {**DEFAULT_PETSC_OPTIONS, **preset, **read_now},
                     checked=tuple(read_now))
        self._shift = None
        if linear_solver in SUBSOLVER_OPTIONS:
            self._preconditioner(mesh)
        self.snes.setJacobian(weak_callback(self._snes_jacobian), self._K, self._K)
        controls = {**(blr_controls(blr_precision) if linear_solver == "iterative" else {}),
                    **{k: v for k, v in user.items() if k.startswith(READ_LATER)}}
        self._set_mumps(controls)

        sigma = self.P * self.F.T / ufl.det(self.F)
        gamma1 = ds(geometry.ends[0])
        # Compiled on first use: a growth tensor on a quadrature space has no values on
        # facets, so with growth these forms cannot be built (and growth runs need none).
        self._reaction_ufl = ufl.dot(sigma * N, N) * gamma1
        self._reaction_current_ufl = ufl.dot(self.P * N, n) * gamma1
        # The end forces along Γ1's mean outward normal d (the axis on flat or symmetric
        # ends). The resultant d·∫_{Γ1} P N dA is taken the variationally consistent way,
        # ∫ P : ∇(ψ d) dX with ψ the P2 function that is 1 at Γ1's nodes and 0 at all
        # others: equal to it in the continuum (div P = 0, the side free of traction),
        # and in the discrete equations to the spring's resultant. The surface integral
        # of the FE stress itself is off by 5 % on the idealized mesh (0.545 N against 0.572 N).
        d = _mean_normal(geometry, geometry.ends[0])
        self.end_axis = d
        d = ufl.as_vector(d.tolist())
        psi = _end_indicator(geometry, geometry.ends[0])
        self._end_force_ufl = ufl.inner(self.P, ufl.grad(psi * d)) * dx
        self._spring_force_ufl = -k * ufl.dot(n, u) * ufl.dot(n, d) * area_ratio * gamma1
        self._reaction = self._reaction_current = self._end_force = self._spring_force = None
        # det F of P2 displacements on affine cells is a cubic, which a rule of degree 3
        # integrates exactly: 6 points a cell instead of the forms' 14 (degree 4) for the
        # same volume to round-off, at half the cost of a growth step's measure
        volume_degree = geometry.quadrature_degree
        if geometry.mesh.geometry.cmaps[0].degree == 1:
            volume_degree = min(volume_degree, EXACT_VOLUME_DEGREE)
        self._volume = fem.form(ufl.det(self.F) * ufl.Measure("dx", domain=geometry.mesh,
                                                              metadata={"quadrature_degree": volume_degree}))
        self.reset()

    # -- the Newton system -------------------------------------------------------------

    def _build_system(self, constraint_forms) -> None:
        """The Newton matrix K and vectors, with one row and column per free rigid mode.

        The unknown vector holds each rank's owned dofs of w, and on the last rank the
        multipliers after them, so the dofs keep the global numbers DOLFINx gives them
        and the Jacobian form assembles straight into K.
        """
        imap = self.W.dofmap.index_map
        bs = self.W.dofmap.index_map_bs
        self._nowned = imap.size_local * bs
        self._b = fem.petsc.create_vector(self.W)
        m = len(constraint_forms)
        self._mult_rank = self.comm.size - 1
        self._nmult = m if self.comm.rank == self._mult_rank else 0
        if m == 0:
            self._K = fem.petsc.create_matrix(self._jacobian_form)
            self._B = np.empty((0, self._nowned))
        else:
            cols = []
            for form in constraint_forms:
                vec = fem.petsc.assemble_vector(form)
                vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
                cols.append(vec.array.copy())
                vec.destroy()
            self._B = np.array(cols)  # (modes, owned dofs)
            N = imap.size_global * bs
            first = imap.local_range[0] * bs
            self._rows = np.arange(first, first + self._nowned, dtype=PETSc.IntType)
            self._mult_index = np.arange(N, N + m, dtype=PETSc.IntType)
            self._K = self._bordered_matrix(N, m)
        self._x, self._F = self._K.createVecs()

    def _bordered_matrix(self, N: int, m: int) -> PETSc.Mat:
        """An AIJ matrix for [[J, B], [Bᵀ, 0]], preallocated exactly: the Jacobian form's
        entries (counted from DOLFINx's sparsity pattern), a column per multiplier in
        every row of w, and dense multiplier rows (last rank). Its first assembly
        (`assemble_jacobian`) fixes the pattern. No Jacobian-sized matrix is made on
        the way: a copy of J would be the largest object of a Krylov solve."""
        if self.W.dofmap.index_map_bs != 1:
            raise RuntimeError(f"the mixed space's dofmap has block size {self.W.dofmap.index_map_bs}, expected 1")
        nrows = self._nowned
        # counted, then the pattern (a third of K's size) freed before K is made
        pattern = fem.create_sparsity_pattern(self._jacobian_form)
        pattern.finalize()
        local_cols, offsets = pattern.graph
        cmap = pattern.index_map(1)
        counts = np.diff(offsets[: nrows + 1]).astype(np.int64)
        ghost_cols = np.zeros(nrows, dtype=np.int64)
        if nrows:
            ghost_cols = np.add.reduceat(local_cols[: offsets[nrows]] >= cmap.size_local, offsets[:nrows])
            ghost_cols[counts == 0] = 0  # reduceat gives the next row's first entry for an empty row
        del local_cols, offsets, pattern
        last = self.comm.rank == self._mult_rank  # its column range holds the multipliers
        d_nnz = counts - ghost_cols + (m if last else 0)
        o_nnz = ghost_cols + (0 if last else m)
        # the multiplier rows: every dof of w (Bᵀ), no diagonal
        d_nnz = np.concatenate([d_nnz, np.full(self._nmult, nrows)])
        o_nnz = np.concatenate([o_nnz, np.full(self._nmult, N - nrows)])
        size = (nrows + self._nmult, N + m)
        K = PETSc.Mat().createAIJ((size, size), nnz=(d_nnz.astype(PETSc.IntType), o_nnz.astype(PETSc.IntType)),
                                  comm=self.comm)
        K.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        to_global = cmap.local_to_global(np.arange(cmap.size_local + cmap.num_ghosts, dtype=np.int32))
        lgmap = PETSc.LGMap().create(np.asarray(to_global, dtype=PETSc.IntType), bsize=1, comm=self.comm)
        K.setLGMap(lgmap, lgmap)
        return K

    def _preconditioner(self, mesh) -> None:
        """The splits and matrices of the "amg" preconditioner (module docstring).

        Displacement split: the owned u dofs node by node (blocks of 3, as GAMG wants),
        with the six rigid motions about the centroid as its near null space, in the
        order of the collapsed P2 space (so "pmg" interpolates into it from P1 directly).
        Its preconditioner is built from the Newton matrix's displacement block.
        Pressure split: the owned p dofs in the order of the collapsed P1 space, then
        (last rank) the multipliers, so that the Schur preconditioner
        Sp = +(1/μ) M_p ⊕ -diag(c) is assembled on the P1 space directly (μ = 2 (c1 + c2),
        the shear modulus). Where rigid motions are free, ε M_u (ε = AMG_SHIFT μ / L², its
        diagonal) added to the extracted block (`_shift_block`) keeps it non-singular and
        c_i = ∫ r_i·r_i dX / ε is the Schur complement Bᵀ (E + ε M_u)⁻¹ B of a motion r_i
        the block E does not resist.
        """
        import dolfinx.fem.petsc  # noqa: F401

        comm = self.comm
        first = self._K.getOwnershipRange()[0]
        Vu, udofs = self.W.sub(0).collapse()
        nu = Vu.dofmap.index_map.size_local
        udofs = np.asarray(udofs, dtype=np.int64).ravel()[: 3 * nu]
        Q, qdofs = self.W.sub(1).collapse()
        nq = Q.dofmap.index_map.size_local
        qdofs = np.asarray(qdofs, dtype=np.int64).ravel()[:nq]
        if udofs.max(initial=-1) >= self._nowned or qdofs.max(initial=-1) >= self._nowned:
            raise RuntimeError("a collapsed space owns a dof its mixed space does not")
        is_u = PETSc.IS().createGeneral((udofs + first).astype(PETSc.IntType), comm=comm)
        is_u.setBlockSize(3)
        m = len(self.rigid.modes)
        mult = self._mult_index[: self._nmult] if m else np.empty(0, dtype=np.int64)
        is_p = PETSc.IS().createGeneral(np.concatenate([qdofs + first, mult]).astype(PETSc.IntType), comm=comm)
        is_u.compose("nearnullspace", _rigid_body_space(Vu.tabulate_dof_coordinates()[:nu], comm))

        mu = 2.0 * (self.material.c1 + self.material.c2)
        dx = self.geometry.dx
        c = np.empty(0)
        if m:
            # elementwise over ranks (the pickling allreduce cannot take MIN of arrays)
            lo, hi = np.empty(3), np.empty(3)
            comm.Allreduce(np.ascontiguousarray(mesh.geometry.x.min(axis=0)), lo, op=MPI.MIN)
            comm.Allreduce(np.ascontiguousarray(mesh.geometry.x.max(axis=0)), hi, op=MPI.MAX)
            eps = AMG_SHIFT * mu / float(np.sum((hi - lo) ** 2))
            c = np.array([self._sum(fem.form(ufl.dot(r, r) * dx)) for r in self.rigid.modes]) / eps
            # diag M_u from the scalar P2 mass matrix (a ninth of the vector one's entries):
            # the same ∫ φ_i² for the three components of a node
            Vs, node_dofs = Vu.sub(0).collapse()
            s = ufl.TrialFunction(Vs)
            Ms = fem.petsc.assemble_matrix(fem.form(s * ufl.TestFunction(Vs) * dx))
            Ms.assemble()
            mass = Ms.getDiagonal()
            Ms.destroy()
            ns = Vs.dofmap.index_map.size_local
            # in the split's numbering (Vu's owned dofs in order), added to the displacement
            # block the fieldsplit extracts (`_shift_block`): a shifted copy of all of K
            # would double the largest matrix of the set-up
            self._shift = PETSc.Vec().createMPI((3 * nu, PETSc.DETERMINE), comm=comm)
            # Vu's local dof of each owned node's first component
            first_node = np.asarray(node_dofs, dtype=np.int64).ravel()[:ns]
            if first_node.max(initial=-1) >= 3 * nu:
                raise RuntimeError("a collapsed space owns a dof its parent does not")
            for component in range(3):
                self._shift.getArray()[first_node + component] = eps * mass.getArray()
            mass.destroy()
            self._shifted_state = None

        p, q = ufl.TrialFunction(Q), ufl.TestFunction(Q)
        Mp = fem.petsc.assemble_matrix(fem.form(p * q * dx))
        Mp.assemble()
        indptr, indices, values = Mp.getValuesCSR()
        Mp.destroy()
        NQ = Q.dofmap.index_map.size_global
        indptr = np.concatenate([indptr, indptr[-1] + np.arange(1, self._nmult + 1)]).astype(PETSc.IntType)
        indices = np.concatenate([indices, NQ + np.arange(self._nmult)]).astype(PETSc.IntType)
        # +M_p/μ: the coupling blocks are nearly antisymmetric, so S = -K[p,u] A⁻¹ K[u,p] ≈ +M_p/μ
        # (the opposite sign doubles the GMRES count: docs/performance.md)
        values = np.concatenate([values / mu, -c[: self._nmult]])
        n = nq + self._nmult
        self._schur = PETSc.Mat().createAIJ(((n, NQ + m), (n, NQ + m)), comm=comm)
        self._schur.setPreallocationCSR((indptr, indices, values))
        self._schur.assemble()
        pc = self.snes.getKSP().getPC()
        pc.setFieldSplitIS(("u", is_u), ("p", is_p))
        pc.setFieldSplitSchurPreType(PETSc.PC.FieldSplitSchurPreType.USER, self._schur)
        self._splits = (is_u, is_p)
        self._split_udofs = udofs
        if self.linear_solver == "pmg":
            # the split's rows are Vu's owned dofs in order, so its numbering is Vu's
            V1 = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
            full = fem.petsc.interpolation_matrix(V1, Vu)
            full.assemble()
            # preallocated for dense cell blocks, 12 times the entries it holds: a copy keeps those alone
            self._prolongation = full.duplicate(copy=True)
            full.destroy()
            self._coarse_modes = _rigid_body_space(V1.tabulate_dof_coordinates()[: V1.dofmap.index_map.size_local],
                                                   comm)

    def setup_linear_solver(self) -> None:
        """Set up the linear solver for the current matrix (factorise it, or build the AMG
        hierarchy): done only where the matrix changed since the last set-up. The first
        set-up of "amg" or "pmg" reads the sub-solvers' options; one of the user's it did not read
        is an InputError, as `_set_options` makes of the others."""
        ksp = self.snes.getKSP()
        ksp.setOperators(self._K, self._K)
        if self._subsolvers_read or not self._subsolver_options:
            ksp.setUp()
            if self._shift_block():  # a new block: its multipliers' Schur with it
                self._multiplier_schur()
            return
        db = PETSc.Options()
        prefix = self.snes.getOptionsPrefix()
        added = [prefix + k for k in self._subsolver_options if not db.hasName(prefix + k)]
        for key, value in self._subsolver_options.items():
            if prefix + key in added:
                db.setValue(prefix + key, value)
        try:
            ksp.setUp()
            self._shift_block()
            if self.linear_solver == "pmg":
                self._coarse_gamg(ksp.getPC().getFieldSplitSubKSP()[0].getPC(), db.hasName(prefix + COARSE_PC))
            for sub in ksp.getPC().getFieldSplitSubKSP():  # GAMG reads its levels' options here
                sub.setUp()
            unused = [k for k in self._user_subsolver_options if not db.used(prefix + k)]
        except PETSc.Error as err:
            what = refused(db, prefix, self._subsolver_options, self._user_subsolver_options, added)
            raise InputError(f"PETSc refused {what}: {_last_line(err)}") from None
        finally:
            for name in added:
                db.delValue(name)
        self._subsolvers_read = True
        self._multiplier_schur()
        if unused:
            raise InputError(f"--petsc-option: PETSc does not read {', '.join(unused)} for the mechanics "
                             "solver's fieldsplit (misspelt, or an option of another object)")

    def _coarse_gamg(self, pc, chosen: bool) -> None:
        """Set the displacement split's p-multigrid up ("pmg"): the P1 → P2 interpolation,
        then GAMG on the Galerkin P1 operator with the rigid motions of the P1 nodes as its
        near null space. That operator exists only once the multigrid is set up, and it is
        kept (values updated) when the Newton matrix changes, and its null space with it.
        ``chosen``: the user named the coarse solver, which then stays as given."""
        if pc.getType() != "mg":
            return  # the options asked for another preconditioner: it wins
        pc.setMGInterpolation(1, self._prolongation)
        coarse = pc.getMGCoarseSolve()
        if chosen:
            return
        coarse.getPC().setType("jacobi")  # a stand-in until the Galerkin operator exists
        pc.setUp()
        coarse.getOperators()[1].setNearNullSpace(self._coarse_modes)
        coarse.getPC().setType("gamg")
        coarse.setFromOptions()
        coarse.setUp()

    def _shift_block(self) -> bool:
        """Add ε M_u (its diagonal) to the displacement block the fieldsplit extracted from
        K, once per extraction: the fieldsplit extracts it anew (values overwritten) when K
        changes, and the block's state tells whether it has the shift already. True where
        it shifted a new block."""
        if self._shift is None:
            return False
        block = self.snes.getKSP().getPC().getFieldSplitSubKSP()[0].getOperators()[1]
        if block.stateGet() == self._shifted_state:
            return False
        block.setDiagonal(self._shift, addv=PETSc.InsertMode.ADD_VALUES)
        self._shifted_state = block.stateGet()
        return True

    def _multiplier_schur(self) -> None:
        """The multipliers' part of the Schur preconditioner, -bᵢᵀ Â⁻¹ bᵢ with Â⁻¹ the
        displacement split's preconditioner and bᵢ = ∫ rᵢ·v dX: the free motions are
        near null vectors of the shifted block, where Â⁻¹ is large; taken with the same
        Â⁻¹ the large parts cancel (as in the Woodbury identity)."""
        if not self._subsolver_options or not len(self.rigid.modes):
            return
        sub = self.snes.getKSP().getPC().getFieldSplitSubKSP()[0]
        upc = sub.getPC()
        b = upc.getOperators()[1].createVecRight()
        z = b.duplicate()
        udofs = self._split_udofs
        c = []
        for row in self._B:
            b.getArray()[:] = row[udofs]
            upc.apply(b, z)
            c.append(b.dot(z))
        if self._nmult:
            rows = self._schur.getOwnershipRange()[1] - self._nmult + np.arange(self._nmult, dtype=PETSc.IntType)
            for row, value in zip(rows, c[len(c) - self._nmult:]):
                self._schur.setValue(row, row, -value)
        self._schur.assemble()
        self.snes.getKSP().getPC().getFieldSplitSubKSP()[1].getPC().setUp()  # its Jacobi takes the new diagonal

    def _set_mumps(self, controls: dict) -> None:
        """Set MUMPS controls (``mat_mumps_icntl_N`` / ``mat_mumps_cntl_N`` keys) on the
        factor object, made now for the purpose: MUMPS reads its -mat_mumps_ options at
        the first factorisation, long after `_set_options` has taken them out of the
        database (where they would reach the next solver made in this process)."""
        if not controls:
            return
        ksp = self.snes.getKSP()
        pc = ksp.getPC()
        if not _is_mumps_lu(pc):
            return  # the options asked for another preconditioner: it wins
        ksp.setOperators(self._K, self._K)
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        for key, value in controls.items():
            kind, _, index = key.removeprefix("mat_mumps_").partition("_")
            try:
                if kind == "icntl":
                    factor.setMumpsIcntl(int(index), int(value))
                elif kind == "cntl":
                    factor.setMumpsCntl(int(index), float(value))
                else:
                    raise ValueError(kind)
            except (ValueError, PETSc.Error):
                raise InputError(f"--petsc-option: {key}={value} is not a MUMPS control "
                                 "(mat_mumps_icntl_N=integer or mat_mumps_cntl_N=number)") from None

    def linear_iterations(self) -> int:
        """Krylov iterations of the last solve (one per Newton step with LU)."""
        return self.snes.getLinearSolveIterations()

    def apply_inverse(self, r: PETSc.Vec, f: PETSc.Vec) -> None:
        """f = K⁻¹ r with the linear solver as last set up (`setup_linear_solver`), for
        Newton iterations outside SNES (`hyper.fem.newton.KeptFactors`). LU and
        "iterative" apply their factors once (the BLR factors are inexact: the kept-factor
        iteration's secants correct them as they correct old factors). "pmg" (and "amg")
        run their GMRES to its tolerance: one application of the fieldsplit is far from
        K⁻¹, and the kept iteration converges as with LU only with K solved as well."""
        ksp = self.snes.getKSP()
        if ksp.getType() == PETSc.KSP.Type.PREONLY:
            ksp.getPC().apply(r, f)
            self.krylov_iterations += 1
            return
        ksp.solve(r, f)
        self.krylov_iterations += ksp.getIterationNumber()
        reason = ksp.getConvergedReason()
        if reason <= 0:
            raise SolverError(f"the linear solver ({self.linear_solver}, {ksp.getType()}) did not converge "
                              f"({_KSP_REASONS.get(reason, reason)}) after {ksp.getIterationNumber()} iterations")

    def mumps_memory(self) -> dict:
        """MUMPS's account of the last factorisation, summed over ranks: memory its
        analysis estimated and the memory it used (MB, INFOG 17 and 22), the entries a
        full-rank factor would have (INFOG 29) and those stored (INFOG 35, fewer with BLR)."""
        pc = self.snes.getKSP().getPC()
        if not _is_mumps_lu(pc):
            return {}
        factor = pc.getFactorMatrix()
        return {"mumps_estimated_mb": factor.getMumpsInfog(17), "mumps_used_mb": factor.getMumpsInfog(22),
                "factor_entries": factor.getMumpsInfog(29), "factor_entries_stored": factor.getMumpsInfog(35)}

    def _set_state(self, x) -> None:
        arr = x.getArray(readonly=True)
        self.w.x.array[: self._nowned] = arr[: self._nowned]
        self.w.x.scatter_forward()
        if len(self.multipliers):
            mine = arr[self._nowned:].copy() if self.comm.rank == self._mult_rank else None
            self.multipliers = self.comm.bcast(mine, root=self._mult_rank)

    def _assemble_residual(self, snes, x, f) -> None:
        self._set_state(x)
        with self._b.localForm() as local:
            local.set(0.0)
        fem.petsc.assemble_vector(self._b, self._residual_form)
        self._b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        out = f.getArray()
        out[: self._nowned] = self._b.array + self.multipliers @ self._B
        if len(self.multipliers):
            constraint = self.comm.allreduce(self._B @ self.w.x.array[: self._nowned], op=MPI.SUM)
            out[self._nowned:] = constraint[: self._nmult]

    def _snes_jacobian(self, snes, x, K, P) -> None:
        self.assemble_jacobian(x)

    # -- public ------------------------------------------------------------------------

    @property
    def jacobian_matrix(self) -> PETSc.Mat:
        """The Newton matrix [[J, B], [Bᵀ, 0]] (an assembled AIJ matrix, rows as in
        `solution_vector`)."""
        return self._K

    @property
    def solution_vector(self) -> PETSc.Vec:
        """The Newton unknowns as SNES sees them: this rank's `owned_size` dofs of w,
        then on the last rank the multipliers."""
        return self._x

    @property
    def owned_size(self) -> int:
        """The dofs of w this rank owns: the first entries of w's local array."""
        return self._nowned

    @property
    def pressure_dofs(self) -> np.ndarray:
        """The positions of the pressure dofs in w's local array (owned, then ghost)."""
        return self._p_dofs

    def assemble_residual(self, x: PETSc.Vec, f: PETSc.Vec) -> None:
        """Take the state (w, μ) from the Newton unknowns ``x`` and assemble the residual
        into ``f`` (a vector like `solution_vector`)."""
        self._assemble_residual(None, x, f)

    def load_state(self, x: PETSc.Vec) -> None:
        """Write the current state (w, μ) into the Newton unknowns ``x``."""
        arr = x.getArray()
        arr[: self._nowned] = self.w.x.array[: self._nowned]
        arr[self._nowned:] = self.multipliers[: self._nmult]

    def assemble_jacobian(self, x: PETSc.Vec) -> None:
        """Take the state (w, μ) from the Newton unknowns ``x`` and assemble
        `jacobian_matrix` there."""
        self._set_state(x)
        K = self._K
        K.zeroEntries()
        fem.petsc.assemble_matrix(K, self._jacobian_form)
        if len(self.multipliers):
            add = PETSc.InsertMode.ADD_VALUES
            K.setValues(self._rows, self._mult_index, self._B.T.copy(), addv=add)
            K.setValues(self._mult_index, self._rows, self._B, addv=add)
        K.assemble()
        if self._subsolvers_read:
            # The fieldsplit's set-up now, not when PETSc next solves: it extracts the
            # blocks anew, and only then can the shift and the multipliers' Schur (which
            # cancels large parts of Â⁻¹ only when taken with it) be made for this matrix
            self.setup_linear_solver()

    @property
    def num_dofs(self) -> int:
        """Unknowns of the Newton system: displacement, pressure and multipliers."""
        return self._K.getSize()[0]

    def reset(self) -> None:
        """The stress-free reference state: u = 0, p = c1 + 2 c2, μ = 0."""
        self.w.x.array[:] = 0.0
        self.w.x.array[self._p_dofs] = mat.reference_pressure(self.material)
        self.w.x.scatter_forward()
        self.multipliers[:] = 0.0

    def start_from(self, other: MechanicsProblem) -> None:
        """Take u, p, μ and α of a problem on another mesh of the same body as the
        initial guess (nested iteration on a refined mesh)."""
        cells = np.arange(self.geometry.mesh.topology.index_map(3).size_local, dtype=np.int32)
        for i in range(2):
            V, dofs = self.W.sub(i).collapse()
            V0, dofs0 = other.W.sub(i).collapse()
            source = fem.Function(V0)
            source.x.array[:] = other.w.x.array[dofs0]
            target = fem.Function(V)
            data = fem.create_interpolation_data(V, V0, cells, padding=1e-10)
            target.interpolate_nonmatching(source, cells, data)
            target.x.scatter_forward()
            self.w.x.array[dofs] = target.x.array
        self.w.x.scatter_forward()
        self.multipliers = other.multipliers.copy()
        self.alpha.value = float(other.alpha.value)

    def solve(self) -> int:
        """Newton from the current state; returns the number of iterations.

        Raises SolverError (state restored) if SNES does not converge.
        """
        previous = self.w.x.array.copy(), self.multipliers.copy()
        x = self._x.getArray()
        x[: self._nowned] = self.w.x.array[: self._nowned]
        x[self._nowned:] = self.multipliers[: self._nmult]
        if not self._subsolvers_read and self._subsolver_options:
            # SNES would set the fieldsplit up without its sub-solvers' options (and an
            # InputError inside its callback would become a PETSc error)
            self.assemble_jacobian(self._x)
            self.setup_linear_solver()
        try:
            self.snes.solve(None, self._x)
            reason = self.snes.getConvergedReason()
        except PETSc.Error as err:
            reason = f"PETSc error {err}"
        iterations = self.snes.getIterationNumber()
        self.krylov_iterations += self.snes.getLinearSolveIterations()
        if not isinstance(reason, int) or reason <= 0:
            self.w.x.array[:] = previous[0]
            self.w.x.scatter_forward()
            self.multipliers = previous[1]
            name = _REASONS.get(reason, reason) if isinstance(reason, int) else reason
            raise SolverError(
                f"Newton did not converge at alpha = {float(self.alpha.value):g} "
                f"after {iterations} iterations ({name}); previous solution restored"
            )
        self._set_state(self._x)
        return iterations

    def _sum(self, form) -> float:
        return self.comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)

    def reaction_force_original(self) -> float:
        """∫_{Γ1} (σN)·N dA on the reference end face (N), as the original code reported it
        (N): Cauchy stress integrated over reference area, no force of the body (MODEL.md §9)."""
        if self._reaction is None:
            self._reaction = fem.form(self._reaction_ufl)
        return self._sum(self._reaction)

    def end_force(self) -> float:
        """d·∫_{Γ1} P N dA: the resultant force on the end Γ1 along its mean outward
        normal d (`end_axis`), positive in tension (N), taken the variationally consistent
        way (see the constructor). In equilibrium it is the `spring_force` less the
        multipliers' share on the cells at Γ1 (zero for a symmetric body)."""
        if self._end_force is None:
            self._end_force = fem.form(self._end_force_ufl)
        return self._sum(self._end_force)

    def spring_force(self) -> float:
        """d·∫_{Γ1} -k (n·u) n |cof F N| dA: the resultant of the tendon spring on Γ1
        along d, positive in tension (N), from the displacement of the end alone."""
        if self._spring_force is None:
            self._spring_force = fem.form(self._spring_force_ufl)
        return self._sum(self._spring_force)

    def reaction_force_current(self) -> float:
        """∫_{Γ1} (PN)·n dA: the force along the current end normal n (N)."""
        if self._reaction_current is None:
            self._reaction_current = fem.form(self._reaction_current_ufl)
        return self._sum(self._reaction_current)

    def volume(self) -> float:
        """∫ det F dX (m³)."""
        return self._sum(self._volume)


EXACT_VOLUME_DEGREE = 3  # of det F for P2 displacements on affine cells


def _is_mumps_lu(pc) -> bool:
    return pc.getType() == "lu" and pc.getFactorSolverType() == "mumps"


def taylor_hood_unknowns(mesh) -> int:
    """Displacement and pressure unknowns of P2-P1 on ``mesh``, without building the space
    (the multipliers of free rigid motions, at most three, not counted). Collective."""
    mesh.topology.create_entities(1)
    vertices = mesh.topology.index_map(0).size_global
    edges = mesh.topology.index_map(1).size_global
    return 3 * (vertices + edges) + vertices


# Read by MUMPS when it factorises, after setFromOptions: whether they are used cannot be
# known when the solver is set up.
READ_LATER = ("mat_mumps_",)
# Read by the fieldsplit's sub-solvers at its first set-up ("amg", "pmg").
SUBSOLVER = "fieldsplit_"


def _set_options(snes, prefix: str, options: dict, checked: tuple[str, ...] = ()) -> None:
    """Apply ``options`` under ``prefix`` except those already in the database, then clean up.

    The ``checked`` keys (the user's) must be ones PETSc reads: a misspelt option would be
    ignored silently, and a bad value would fail deep inside the run. InputError otherwise.
    """
    db = PETSc.Options()
    added = []
    for key, value in options.items():
        name = prefix + key
        if not db.hasName(name):
            db.setValue(name, value)
            added.append(name)
    try:
        snes.setFromOptions()
        unused = [key for key in checked if not key.startswith(READ_LATER) and not db.used(prefix + key)]
    except PETSc.Error as err:
        what = refused(db, prefix, options, checked, added)
        for name in list(db.getAll()):
            if name.startswith(prefix):  # the job stops: PETSc would list them as unused at exit, on stdout
                db.delValue(name)
        raise InputError(f"PETSc refused {what}: {_last_line(err)}") from None
    finally:
        for name in added:
            db.delValue(name)
    if unused:
        raise InputError(f"--petsc-option: PETSc does not read {', '.join(unused)} for the mechanics solver "
                         "(misspelt, or an option of another object)")


def _last_line(err: PETSc.Error) -> str:
    """What PETSc said was wrong: its message is its call stack, and the last line says it."""
    lines = [line.removeprefix("[0]").strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1]


def refused(db, prefix: str, options: dict, checked: tuple[str, ...], added: list[str]) -> str:
    """The options PETSc may have refused, each as the user gave it: ``--petsc-option KEY=VALUE``
    for the ``checked`` keys (the option of the jobs that have one), ``-PREFIXKEY VALUE`` for
    those the options database held already (a job's command line, PETSC_OPTIONS). Never
    blank: where the user gave none, PETSc refused this module's own defaults (a bug)."""
    given = [f"--petsc-option {key}={options[key]}" for key in checked]
    held = {name: value for name, value in db.getAll().items()
            if name.startswith(prefix) and name not in added and name.removeprefix(prefix) not in checked}
    given += [f"-{name} {value or ''}".rstrip() for name, value in sorted(held.items())]  # a flag: no value
    return ", ".join(given) if given else f"the mechanics solver's default options ({prefix}…)"


# ------------------------------------------------------------------- rigid motions


def _rigid_body_space(x: np.ndarray, comm) -> PETSc.NullSpace:
    """The six rigid motions at the nodes ``x`` (owned, in order) as vectors of blocks of
    three, orthonormalised: the near null space of elasticity that GAMG coarsens with."""
    centre = comm.allreduce(x.sum(axis=0), op=MPI.SUM) / comm.allreduce(len(x), op=MPI.SUM)
    vectors = []
    for k in range(6):
        vec = PETSc.Vec().createMPI((3 * len(x), PETSc.DETERMINE), bsize=3, comm=comm)
        values = np.zeros((len(x), 3))
        if k < 3:
            values[:, k] = 1.0
        else:
            values[:] = np.cross(np.eye(3)[k - 3], x - centre)
        vec.getArray()[:] = values.ravel()
        for previous in vectors:
            vec.axpy(-vec.dot(previous), previous)
        vec.normalize()
        vectors.append(vec)
    return PETSc.NullSpace().create(vectors=vectors, comm=comm)


def _end_facets(geometry: Geometry, tag: int):
    """Unit normals, areas and centroids of the owned facets with ``tag``."""
    mesh = geometry.mesh
    facets = geometry.facet_tags.find(tag)
    facets = facets[facets < mesh.topology.index_map(2).size_local]
    pts = mesh.geometry.x[dmesh.entities_to_geometry(mesh, 2, facets)].reshape(-1, 3, 3)
    cross = np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0])
    twice_area = np.linalg.norm(cross, axis=1)
    return cross / twice_area[:, None], 0.5 * twice_area, pts.mean(axis=1)


def _end_indicator(geometry: Geometry, tag: int) -> fem.Function:
    """The P2 scalar function that is 1 at the nodes of the facets with ``tag``, 0 elsewhere."""
    from dolfinx import la

    mesh = geometry.mesh
    psi = fem.Function(fem.functionspace(mesh, ("Lagrange", 2)))
    psi.x.array[fem.locate_dofs_topological(psi.function_space, 2, geometry.facet_tags.find(tag))] = 1.0
    # a rank that holds a node but not its facet learns it from the owner
    psi.x.scatter_reverse(la.InsertMode.add)
    psi.x.array[:] = psi.x.array > 0
    psi.x.scatter_forward()
    return psi


def _mean_normal(geometry: Geometry, tag: int) -> np.ndarray:
    """The unit vector along ∫ N dA, N the outward normal, over the facets with ``tag``."""
    N = ufl.FacetNormal(geometry.mesh)
    ds = ufl.Measure("ds", domain=geometry.mesh, subdomain_data=geometry.facet_tags, metadata=geometry.metadata)
    total = np.array([geometry.comm.allreduce(fem.assemble_scalar(fem.form(N[i] * ds(tag))), op=MPI.SUM)
                      for i in range(3)])
    return total / np.linalg.norm(total)


def rigid_mode_stiffness(geometry: Geometry):
    """The springs' stiffness for rigid motions: eigenvalues (ascending, largest = 1),
    eigenvectors, the centre c and length scale L of the parametrisation.

    A rigid motion t + ω × (X - c) stretches the springs by n·t + ω·((X - c) × n); the
    quadratic form ∫_{ends} (n·t + (ω L)·((X - c) × n) / L)² dA in (t, ωL) is a 6×6
    matrix whose (near-)zero eigenvalues are the motions the ends leave free.
    """
    comm = geometry.comm
    data = [_end_facets(geometry, tag) for tag in geometry.ends]
    area = comm.allreduce(sum(a.sum() for _, a, _ in data), op=MPI.SUM)
    centre = comm.allreduce(sum((a[:, None] * c).sum(axis=0) for _, a, c in data), op=MPI.SUM) / area
    size2 = comm.allreduce(sum((a * ((c - centre) ** 2).sum(axis=1)).sum() for _, a, c in data), op=MPI.SUM)
    size = float(np.sqrt(size2 / area))
    K = np.zeros((6, 6))
    for normals, areas, centroids in data:
        g = np.hstack([normals, np.cross(centroids - centre, normals) / size])
        K += (areas[:, None] * g).T @ g
    K = comm.allreduce(K, op=MPI.SUM)
    # One rank decides, so every rank builds the same constraints.
    eig, vec = comm.bcast(np.linalg.eigh(K) if comm.rank == 0 else None, root=0)
    return eig / eig[-1], vec, centre, size


def rigid_modes(geometry: Geometry) -> RigidModes:
    """The rigid motions the end springs leave free (null space of `rigid_mode_stiffness`)."""
    eig, vec, centre, size = rigid_mode_stiffness(geometry)
    free = np.flatnonzero(eig < FREE_MODE_RATIO)
    ratio = float(eig[0])
    if len(free) == 0:
        return RigidModes((), f"none needed: the springs on the ends resist every rigid motion "
                              f"(smallest/largest stiffness {ratio:.1e})", ratio)
    X = ufl.SpatialCoordinate(geometry.mesh)
    c = ufl.as_vector(centre.tolist())
    modes = []
    names = []
    for j in free:
        t, omega = vec[:3, j], vec[3:, j] / size
        modes.append(ufl.as_vector(t.tolist()) + ufl.cross(ufl.as_vector(omega.tolist()), X - c))
        names.append(_mode_name(t, omega * size))
    return RigidModes(
        tuple(modes),
        f"{len(free)} free rigid motion(s) removed by Lagrange multipliers (∫ u·r dX = 0): "
        + "; ".join(names),
        ratio,
    )


def _mode_name(t, omega) -> str:
    def fmt(a):
        a = np.where(np.abs(a) < 1e-12, 0.0, a)
        return np.array2string(a, precision=3, suppress_small=True)

    if np.linalg.norm(omega) < 1e-8:
        return f"translation {fmt(t)}"
    return f"rotation about {fmt(omega / np.linalg.norm(omega))}" + (
        f" + translation {fmt(t)}" if np.linalg.norm(t) > 1e-8 else ""
    )
