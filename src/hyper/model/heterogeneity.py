"""Per-cell heterogeneity of the signaling parameters (MODEL.md §6).

Each of the twelve rate constants p0 of ``PERTURBED`` becomes a cell field
p = p0 (1 + ε ξ) with ξ uniformly distributed on (-1, 1) at every cell. Two models of
how ξ varies in space:

- ``uniform-noise`` (the paper): ξ independent from cell to cell. Its length scale is
  the mesh's: refining the mesh makes the field rougher.
- ``matern``: ξ = erf(z/√2) of a stationary Gaussian Matérn field z of unit variance,
  smoothness ν and correlation range ℓ, evaluated at the cell midpoints. The marginal
  law of ξ is the same U(-1, 1) as above, so only the spatial structure differs.
  Correlation ρ(r) = 2^{1-ν}/Γ(ν) (κr)^ν K_ν(κr) with κ = √(8ν)/ℓ: at r = ℓ it has
  fallen to about 0.13 (Lindgren, Rue and Lindström 2011's "range").

How z is made: circulant embedding (Dietrich and Newsam 1997) on a regular grid that
covers the mesh's bounding box plus a margin of ``PADDING`` ranges. The covariance at
the grid lags, taken periodically, is diagonalised by the FFT; a sample is
FFT⁻¹(√λ · FFT(white noise)), whose covariance at the grid nodes is the Matérn one
exactly (up to the small negative eigenvalues that are clipped, whose share is
recorded); between nodes a cubic spline interpolates (grid spacing ℓ/``NODES_PER_RANGE``).
The cell value is the field at the cell's midpoint, a point value, so the statistics of
the cell field do not depend on the mesh at all, and the field has no boundary
artefacts: it is a stationary field on R³ seen through the body.

Why not the SPDE (κ² − Δ)^{α/2} z = W on the mesh with P1 elements (Lindgren et al.),
which was tried first: (1) in 3-D α = 2 gives ν = 1/2 (exponential covariance), ν = 1
would need α = 5/2; (2) the discrete field is smoother than the Matérn field unless
h ≪ 1/κ: with α = 4 (ν = 5/2) on box meshes of size h = ℓ/4 and ℓ/8, the correlation
at ℓ/2 came out 0.63 and 0.57 instead of 0.52 (the range 20 % and 9 % too long) and
the P1 variance 0.81 and 0.96 of the target; on the anatomical meshes (h ≈ 6 mm) that
rules out ranges below about 60 mm; (3) natural boundary conditions double the
variance at the surface (a Robin term β = κ repairs it exactly for α = 2 on a flat
boundary, β = 1.2 κ then Neumann to 2.5 % for α = 4). The grid field has none of
these issues and costs a few FFTs of ~10⁵ nodes for the muscles here; the SPDE would
be the choice for meshes much larger than their correlation range, or for
correlation along curved fibres.

Seeding. Every random number belongs to a global identity, never to a rank's local
numbering, and comes from a counter-based generator (Philox) keyed by
(seed, stream, parameter): independent noise is drawn for the whole input mesh and
indexed by the cells' input-file indices (``mesh.topology.original_cell_index``); the
Matérn grid is derived from the global bounding box and drawn whole on every rank.
Both fields are therefore bitwise the same on any number of ranks.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI
from scipy import fft, ndimage, special

from hyper.core.params import InputError, as_seed, finite, shown
from hyper.model.signaling import SignalingParams

PERTURBED = ("a10", "a20", "a3", "a4", "b1", "b2", "b3", "b4", "c21", "c32", "c42", "c43")
MODELS = ("uniform-noise", "matern")

# Random streams: one per (seed, purpose, parameter), so no two uses share numbers.
UNIFORM_STREAM = 0
GRID_NOISE_STREAM = 1

# Grid nodes per correlation range: the cubic spline between nodes then keeps the
# variance within 1 % for ν >= 1 (checked in the tests).
NODES_PER_RANGE = 8
# Margin added to the bounding box, in ranges: points of the body are at least this far
# apart across the periodic wrap, where the correlation is below 0.02 for ν >= 1.
PADDING = 2.0


@dataclass(frozen=True)
class Heterogeneity:
    """How the signaling parameters vary from cell to cell."""

    model: str = "uniform-noise"  # uniform-noise or matern
    epsilon: float = 0.01  # -, relative half-width: p = p0 (1 + ε ξ), ξ ∈ (-1, 1)
    length: float = 0.02  # m, Matérn correlation range ℓ (matern only)
    nu: float = 1.0  # -, Matérn smoothness ν (matern only)

    def __post_init__(self):
        if self.model not in MODELS:
            raise InputError(f"heterogeneity model must be one of {', '.join(MODELS)}, got {self.model!r}")
        for name, low, high in (("epsilon", 0.0, 1.0), ("length", 0.0, math.inf), ("nu", 0.0, 10.0)):
            value = getattr(self, name)
            ok = not isinstance(value, bool) and isinstance(value, (int, float)) and finite(value)
            if not ok or not (low <= value < high) or (name != "epsilon" and value == 0):
                bounds = "[0, 1) (p = p0 (1 + ε ξ) stays positive)" if name == "epsilon" else f"({low:g}, {high:g})"
                raise InputError(f"{name} must be a number in {bounds}, got {shown(value)}")

    def label(self) -> str:
        """A file-name-safe tag, e.g. uniform-noise_eps0.01 or matern_eps0.1_l0.02_nu1."""
        tag = f"{self.model}_eps{self.epsilon:g}"
        return tag + (f"_l{self.length:g}_nu{self.nu:g}" if self.model == "matern" else "")

    def attributes(self) -> dict:
        out = dataclasses.asdict(self)
        if self.model != "matern":
            del out["length"], out["nu"]
        return out


# --------------------------------------------------------------------------- random numbers


def generator(seed: int, stream: int, k: int) -> np.random.Generator:
    """The Philox generator of parameter k in a stream of a seed."""
    seed = as_seed(seed, "seed")
    return np.random.Generator(np.random.Philox(np.random.SeedSequence([int(seed), stream, k])))


def uniform_noise(cells: np.ndarray, n_global: int, seed: int, count: int = len(PERTURBED)) -> np.ndarray:
    """ξ ~ U(-1, 1), shape (count, len(cells)): row k for parameter k at the given global cells."""
    return np.array([generator(seed, UNIFORM_STREAM, k).uniform(-1.0, 1.0, n_global)[cells] for k in range(count)])


def uniform_marginal(z) -> np.ndarray:
    """erf(z/√2) = 2Φ(z) − 1: U(-1, 1) where z ~ N(0, 1)."""
    return special.erf(np.asarray(z, dtype=float) / math.sqrt(2.0))


def perturb(base: SignalingParams, xi: np.ndarray, epsilon: float) -> SignalingParams:
    """base with p = p0 (1 + ε ξ_k) for the k-th parameter of PERTURBED; xi (12, n)."""
    xi = np.asarray(xi, dtype=float)
    if xi.ndim != 2 or xi.shape[0] != len(PERTURBED):
        raise ValueError(f"xi must have shape ({len(PERTURBED)}, n), got {xi.shape}")
    changes = {}
    for name, row in zip(PERTURBED, xi):
        p0 = getattr(base, name)
        if np.ndim(p0):
            raise InputError(f"{name}: the base value of a perturbed parameter must be a single number")
        changes[name] = p0 * (1.0 + epsilon * row)
    return dataclasses.replace(base, **changes)


# --------------------------------------------------------------------------------- Matérn


def matern_kappa(length: float, nu: float) -> float:
    """κ = √(8ν)/ℓ for the range ℓ."""
    return math.sqrt(8.0 * nu) / length


def matern_correlation(r, length: float, nu: float) -> np.ndarray:
    """ρ(r) = 2^{1-ν}/Γ(ν) (κr)^ν K_ν(κr), ρ(0) = 1."""
    x = matern_kappa(length, nu) * np.abs(np.asarray(r, dtype=float))
    safe = np.where(x > 0, x, 1.0)
    rho = 2.0 ** (1.0 - nu) / math.gamma(nu) * safe**nu * special.kv(nu, safe)
    return np.where(x > 0, rho, 1.0)


class MaternGrid:
    """Unit-variance Matérn samples on a periodic grid covering the box [lower, upper].

    Pure numpy: the grid follows from the box, the range and ν alone, and a sample from
    (seed, k) alone, so every process that builds the same grid draws the same field.
    """

    def __init__(self, lower, upper, length: float, nu: float = 1.0, *,
                 nodes_per_range: int = NODES_PER_RANGE, padding: float = PADDING):
        Heterogeneity(model="matern", length=length, nu=nu)  # validates length and ν
        self.lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        self.length, self.nu = float(length), float(nu)
        self.spacing = length / nodes_per_range
        extent = upper - self.lower + padding * length
        self.shape = tuple(fft.next_fast_len(int(math.ceil(e / self.spacing)), real=True) for e in extent)
        # Periodic lags: the distance to the nearest image of the origin along each axis.
        lags = [np.minimum(np.arange(n), n - np.arange(n)) * self.spacing for n in self.shape]
        r = np.sqrt(lags[0][:, None, None] ** 2 + lags[1][None, :, None] ** 2 + lags[2][None, None, :] ** 2)
        eigen = fft.rfftn(matern_correlation(r, length, nu)).real
        # A padded Matérn circulant is nearly positive semidefinite; what is negative is
        # dropped and the variance put back to one.
        self.clipped = float(-eigen[eigen < 0].sum() / np.abs(eigen).sum())
        eigen = np.maximum(eigen, 0.0)
        size = float(np.prod(self.shape))
        # rfftn keeps half of the last axis: weight the modes it stands for twice.
        weight = np.full(eigen.shape[-1], 2.0)
        weight[0] = 1.0
        if self.shape[-1] % 2 == 0:
            weight[-1] = 1.0
        total = float((eigen * weight).sum())
        self._root = np.sqrt(eigen * size / total)

    def field(self, seed: int, k: int = 0) -> np.ndarray:
        """The grid values of sample (seed, k), shape ``self.shape``."""
        noise = generator(seed, GRID_NOISE_STREAM, k).standard_normal(self.shape)
        return fft.irfftn(self._root * fft.rfftn(noise), s=self.shape)

    def at(self, values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Cubic-spline interpolation of grid values at points (n, 3)."""
        index = ((np.asarray(points, dtype=float) - self.lower) / self.spacing).T
        return ndimage.map_coordinates(values, index, order=3, mode="grid-wrap")

    def sample(self, seed: int, k: int, points: np.ndarray) -> np.ndarray:
        return self.at(self.field(seed, k), points)


# ------------------------------------------------------------------------------ on a mesh


def cell_identity(mesh) -> tuple[np.ndarray, int]:
    """(the input-file index of each owned cell, the number of cells in the file)."""
    n = mesh.topology.index_map(mesh.topology.dim).size_local
    original = np.asarray(mesh.topology.original_cell_index[:n], dtype=np.int64)
    n_global = mesh.comm.allreduce(int(original.max()) + 1 if n else 0, op=MPI.MAX)
    return original, n_global


def cell_midpoints(mesh) -> np.ndarray:
    """Midpoints (mean of the vertices) of the owned cells, in local order, shape (n, 3)."""
    from dolfinx import mesh as dmesh

    tdim = mesh.topology.dim
    n = mesh.topology.index_map(tdim).size_local
    nodes = dmesh.entities_to_geometry(mesh, tdim, np.arange(n, dtype=np.int32))
    return mesh.geometry.x[nodes].mean(axis=1)


def matern_grid(mesh, spec: Heterogeneity) -> MaternGrid:
    """The grid for a mesh: its global bounding box, the same on every rank."""
    x = mesh.geometry.x
    lower, upper = np.empty(3), np.empty(3)
    mesh.comm.Allreduce(x.min(axis=0) if len(x) else np.full(3, np.inf), lower, op=MPI.MIN)
    mesh.comm.Allreduce(x.max(axis=0) if len(x) else np.full(3, -np.inf), upper, op=MPI.MAX)
    return MaternGrid(lower, upper, spec.length, spec.nu)


def cell_xi(mesh, spec: Heterogeneity, seed: int) -> np.ndarray:
    """ξ for every perturbed parameter at the owned cells, shape (12, n_owned)."""
    if spec.model == "uniform-noise":
        cells, n_global = cell_identity(mesh)
        return uniform_noise(cells, n_global, seed)
    grid = matern_grid(mesh, spec)
    points = cell_midpoints(mesh)
    return np.array([uniform_marginal(grid.sample(seed, k, points)) for k in range(len(PERTURBED))])


def cell_params(mesh, spec: Heterogeneity, seed: int, base: SignalingParams | None = None) -> SignalingParams:
    """Per-owned-cell signaling parameters of sample ``seed`` (cells in local order)."""
    base = SignalingParams() if base is None else base
    return perturb(base, cell_xi(mesh, spec, seed), spec.epsilon)
