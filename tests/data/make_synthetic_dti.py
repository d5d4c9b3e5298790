"""Make tests/data/synthetic_dti_TA_VHF_Right.nii.gz: a synthetic DTI primary-eigenvector
image of the right tibialis anterior of the Visible Human Female (TA_VHF_Right), in the
mesh's world frame (mm), with a known bipennate fibre field, noise and a tissue mask.

    python tests/data/make_synthetic_dti.py          # rewrites the image (needs nibabel)

The field (`field`): in the muscle's principal frame (e1 its long axis, e2 the widest
spread across it, from the centre of its nodes), the fibres lie in the e1-e2 plane at
the pennation angle θ(y) = θmax tanh(y / w) to e1, y the coordinate along e2: a central
aponeurosis at y = 0 with fascicles running away from it on both sides (θmax = 25°,
w = 5 mm). Voxels of 2.5 mm; the tissue mask: the voxels within 2.5 mm of a mesh node;
Gaussian noise of 0.02 on each component before normalising; stored as int16 scaled by
1/10000 (the NIfTI scl_slope). The seed is fixed, so the file is the same on every run.
"""

from __future__ import annotations

import functools
from pathlib import Path

import h5py
import numpy as np
from scipy.spatial import cKDTree

HERE = Path(__file__).resolve().parent
MESH = HERE.parents[1] / "meshes/VHF_Right_Muscle_TibialisAnterior_smooth/VHF_Right_Muscle_TibialisAnterior_smooth.h5"
IMAGE = HERE / "synthetic_dti_TA_VHF_Right.nii.gz"
GEOMETRY = "TA_VHF_Right"
VOXEL_MM = 2.5
THETA_MAX_DEG = 25.0
WIDTH_MM = 5.0
NOISE = 0.02
SEED = 34


@functools.cache
def nodes_mm() -> np.ndarray:
    with h5py.File(MESH, "r") as f:
        return f["Mesh/Grid/geometry"][()]


def frame(x_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre, rows e1, e2, e3) of the principal frame of the nodes (mm)."""
    centre = x_mm.mean(axis=0)
    axes = np.linalg.svd(x_mm - centre, full_matrices=False)[2]
    return centre, axes


def field(x_mm: np.ndarray) -> np.ndarray:
    """The unit fibres at points (n, 3) in mm (sign: along +e1)."""
    centre, (e1, e2, _) = frame(nodes_mm())
    y = (x_mm - centre) @ e2
    theta = np.radians(THETA_MAX_DEG) * np.tanh(y / WIDTH_MM)
    return np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2


def make() -> Path:
    import nibabel

    x = nodes_mm()
    low, high = x.min(axis=0) - 2 * VOXEL_MM, x.max(axis=0) + 2 * VOXEL_MM
    shape = np.ceil((high - low) / VOXEL_MM).astype(int) + 1
    ijk = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1).reshape(-1, 3)
    world = low + ijk * VOXEL_MM
    tissue = cKDTree(x).query(world, distance_upper_bound=VOXEL_MM)[0] <= VOXEL_MM
    rng = np.random.default_rng(SEED)
    v = field(world[tissue]) + NOISE * rng.standard_normal((tissue.sum(), 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    values = np.zeros((len(world), 3))
    values[tissue] = v
    affine = np.diag([VOXEL_MM, VOXEL_MM, VOXEL_MM, 1.0])
    affine[:3, 3] = low
    image = nibabel.Nifti1Image(np.round(values.reshape(*shape, 3) * 1e4).astype(np.int16), affine)
    image.header.set_xyzt_units("mm")
    image.header.set_slope_inter(1e-4, 0.0)
    image.header["descrip"] = b"hyper synthetic DTI V1, TA_VHF_Right"
    nibabel.save(image, IMAGE)
    return IMAGE


if __name__ == "__main__":
    path = make()
    print(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB)")
