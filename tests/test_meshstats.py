"""Mesh statistics: one mesh against fixed and independently computed numbers, the group
means against the paper, the CLI, and 2 ranks against 1."""

import csv

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.commands import meshstats as meshstats_job
from hyper.fem import geometry as geo
from hyper.fem import meshstats

NAME = "BFLH_VHF_Left"
# Computed once with this code (serial); cells/vertices are exact, the rest to rounding.
FIXED = {"cells": 8512, "vertices": 2456, "volume_cm3": 181.83657317202798,
         "csa0_cm2": 11.88134969606373, "length_cm": 25.208441354247114,
         "csa_solid_cm2": 11.834320058051247, "length_solid_cm": 25.132514249037648}


def close(a, b, rtol):
    return abs(a - b) <= rtol * abs(b)


@pytest.fixture(scope="module")
def serial_row():
    return meshstats.statistics(geo.load(NAME, MPI.COMM_SELF))


def test_one_mesh_against_fixed_numbers(serial_row):
    row = serial_row
    assert (row["muscle"], row["subject"], row["side"]) == ("BFLH", "VHF", "Left")
    assert row["cells"] == FIXED["cells"] and row["vertices"] == FIXED["vertices"]
    assert close(row["volume_cm3"], FIXED["volume_cm3"], 1e-10)
    assert close(row["csa0_cm2"], FIXED["csa0_cm2"], 1e-10)
    assert close(row["length_cm"], FIXED["length_cm"], 1e-12)
    assert close(row["csa_solid_cm2"], FIXED["csa_solid_cm2"], 1e-10)
    assert close(row["length_solid_cm"], FIXED["length_solid_cm"], 1e-10)


def test_one_mesh_against_the_raw_file(serial_row):
    """Volume and length recomputed from the XDMF's HDF5 arrays (millimetres) with numpy."""
    path = geo.MESHES_DIR / geo.GEOMETRIES[NAME]
    with h5py.File(path.with_suffix(".h5"), "r") as f:
        x = f["Mesh/Grid/geometry"][()]
        cells = f["Mesh/Grid/topology"][()]
    corners = x[cells]
    volume_mm3 = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])).sum() / 6.0
    assert close(serial_row["volume_cm3"], volume_mm3 / 1e3, 1e-12)
    used = x[np.unique(cells)]
    centred = used - used.mean(axis=0)
    axis = np.linalg.eigh(centred.T @ centred)[1][:, -1]
    along = centred @ axis
    assert close(serial_row["length_cm"], (along.max() - along.min()) / 10.0, 1e-10)
    assert serial_row["vertices"] == len(used) == len(x)
    # The solid's frame by a 4-point rule per cell, exact for the quadratic second moments.
    volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
    a, b = (5 + 3 * 5**0.5) / 20, (5 - 5**0.5) / 20
    points = [a * corners[:, i] + b * (corners.sum(axis=1) - corners[:, i]) for i in range(4)]
    centroid = sum(volume @ p for p in points) / (4 * volume.sum())
    inertia = sum(np.einsum("n,ni,nj->ij", volume, p - centroid, p - centroid) for p in points)
    axis = np.linalg.eigh(inertia)[1][:, -1]
    along = x @ axis
    assert close(serial_row["length_solid_cm"], (along.max() - along.min()) / 10.0, 1e-10)
    assert abs(axis @ np.linalg.eigh(centred.T @ centred)[1][:, -1]) < np.cos(np.radians(1))  # 2° from the vertices'


def test_cli_group_means_match_the_paper(tmp_path):
    out = tmp_path / "stats.csv"
    assert meshstats_job.main(["--output", str(out)]) == 0
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(meshstats.COLUMNS)
    assert [r["geometry"] for r in rows] == list(geo.ANATOMICAL)
    for row in rows:
        for key in ("volume_cm3", "csa0_cm2", "length_cm"):
            row[key] = float(row[key])
    means = meshstats.group_means(rows)
    # The paper reports 0.1 cm³: the means agree to all the digits it gives.
    assert {m: round(v, 1) for m, v in means.items()} == meshstats.PAPER_VOLUME_CM3
    assert all(abs(means[m] - v) < 0.05 for m, v in meshstats.PAPER_VOLUME_CM3.items())
    one = next(r for r in rows if r["geometry"] == NAME)
    assert close(one["volume_cm3"], FIXED["volume_cm3"], 1e-10)
    assert out.with_suffix(".png").is_file()


def test_cli_rejects_bad_output(tmp_path, capsys):
    assert meshstats_job.main(["--output", str(tmp_path / "stats.txt")]) == 2
    assert "stats.txt: expected a .csv file" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_matching_digits():
    assert meshstats.matching_digits(252.3726, 252.4) == 4
    assert meshstats.matching_digits(252.46, 252.4) == 3
    assert meshstats.matching_digits(190.1142, 190.1) == 4


@pytest.mark.mpi
def test_two_ranks_equal_serial():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    parallel = meshstats.statistics(geo.load(NAME, comm))
    serial = meshstats.statistics(geo.load(NAME, MPI.COMM_SELF))
    assert parallel["cells"] == serial["cells"] == FIXED["cells"]
    assert parallel["vertices"] == serial["vertices"] == FIXED["vertices"]
    assert parallel["length_cm"] == serial["length_cm"]  # the same vertices, the same plane
    for key in ("volume_cm3", "csa0_cm2", "csa_solid_cm2", "length_solid_cm"):  # sums in another order
        assert close(parallel[key], serial[key], 1e-12)
