"""Fibres from data (issue 34, part 1): each reader recovers a known field on a shipped
mesh (TA_VHF_Right, 2388 nodes), each malformed input is refused with its message and
nothing written, and the field on two ranks equals the serial one bit for bit.

The known fields: the bipennate field of the shipped synthetic image
(tests/data/make_synthetic_dti.py: pennation θmax tanh(y/w) about a central aponeurosis)
and a fanning field (the pennation angle growing linearly across the muscle) for the
tensor image."""

from __future__ import annotations

import json
import sys
import zlib
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import study
from hyper.commands import cohort as cohort_job
from hyper.commands import contraction as contraction_job
from hyper.commands import fibers as fibers_job
from hyper.commands import grow
from hyper.commands import inspect as inspect_job
from hyper.commands import mesh as mesh_job
from hyper.core.params import InputError
from hyper.fem import fiberdata, fibers
from hyper.fem import fiberread as fr
from hyper.fem import geometry as geo
from hyper.model import protocols
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, provenance, runspec

sys.path.insert(0, str(Path(__file__).parent / "data"))
import make_synthetic_dti as synthetic  # noqa: E402

NAME = synthetic.GEOMETRY
IMAGE = synthetic.IMAGE


@pytest.fixture(scope="module")
def ta():
    return geo.load(NAME, MPI.COMM_SELF)


def nodal(a0):
    n = a0.function_space.dofmap.index_map.size_local
    return a0.function_space.tabulate_dof_coordinates()[:n], a0.x.array.reshape(-1, 3)[:n]


def errors(a0, exact) -> np.ndarray:
    """Angles (°) between a0 and the exact field (a function of points in mm) at the nodes."""
    x, a = nodal(a0)
    return fiberdata.angles(a, exact(x * 1e3))


def frame():
    return synthetic.frame(synthetic.nodes_mm())


def fanning(x_mm):
    """A fanning field: the pennation angle grows linearly from -20° to 20° across e2."""
    centre, (e1, e2, _) = frame()
    y = (x_mm - centre) @ e2
    theta = np.radians(20.0) * np.clip(y / 15.0, -1.0, 1.0)
    return np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2


def nifti(path, values, affine, **header):
    nibabel = pytest.importorskip("nibabel")
    image = nibabel.Nifti1Image(values.astype(np.float32), affine)
    image.header.set_xyzt_units(header.pop("unit", "mm"))
    if "intent" in header:
        image.header.set_intent(header.pop("intent"))
    nibabel.save(image, path)
    return path


def grid(spacing_mm=2.5, pad_mm=5.0):
    """(world points (n, 3) mm, shape, affine) of a grid around the TA."""
    x = synthetic.nodes_mm()
    low = x.min(axis=0) - pad_mm
    shape = np.ceil((x.max(axis=0) + pad_mm - low) / spacing_mm).astype(int) + 1
    ijk = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1).reshape(-1, 3)
    affine = np.diag([spacing_mm] * 3 + [1.0])
    affine[:3, 3] = low
    return low + ijk * spacing_mm, tuple(shape), affine


def tensors(a, fa_high=True):
    """Diffusion tensors (mm²/s) with primary direction a: eigenvalues 1.7e-3 and 0.4e-3 (FA 0.66)
    or, where not ``fa_high``, isotropic 0.8e-3 (FA 0)."""
    d = 0.4e-3 * np.eye(3) + 1.3e-3 * a[:, :, None] * a[:, None, :]
    d[~np.broadcast_to(fa_high, len(a))] = 0.8e-3 * np.eye(3)
    return d


# ---------------------------------------------------------------------------- readers


def test_the_shipped_image_is_recovered_within_2_degrees(ta):
    pytest.importorskip("nibabel")
    a0, field = fiberdata.make(ta, fr.Source(IMAGE))
    err = errors(a0, synthetic.field)
    assert np.percentile(err, 95) < 2.0 and err.mean() < 1.0
    assert field.coverage == 1.0
    x, a = nodal(a0)
    assert np.abs(np.linalg.norm(a, axis=1) - 1).max() < 1e-12
    assert np.all(a @ field.line_of_action > 0)  # along the line of action: the field is within 90° of it
    # the pennation angle: |θ| of the field at the nodes, to within the noise
    exact = fiberdata.angles(synthetic.field(x * 1e3), field.line_of_action)
    assert abs(field.report["pennation"]["mean_deg"] - exact.mean()) < 0.5
    assert field.report["against_stokes"] == "no Stokes fibres to compare with"


def test_a_tensor_image_with_a_mask_and_low_anisotropy_is_recovered_and_filled(ta, tmp_path):
    world, shape, affine = grid()
    a = fanning(world)
    centre, (e1, _, _) = frame()
    along = (world - centre) @ e1
    tissue = along < 60.0  # no image beyond 6 cm from the centre: those nodes are filled
    isotropic = np.abs(along + 40.0) < 8.0  # a band of FA 0: filled too
    d = tensors(a, ~isotropic)
    rng = np.random.default_rng(1)
    d += 1e-5 * rng.standard_normal(d.shape)
    d = (d + np.swapaxes(d, 1, 2)) / 2
    d[~tissue] = 0.0
    fsl = np.stack([d[:, i, j] for i, j in fr.FSL_ORDER], axis=-1).reshape(*shape, 6)
    path = nifti(tmp_path / "tensor.nii.gz", fsl, affine)
    a0, field = fiberdata.make(ta, fr.Source(path, min_fa=0.2))
    x, _ = nodal(a0)
    y = (x * 1e3 - centre) @ e1
    err = errors(a0, fanning)
    sampled = (y < 60.0 - 2.5) & (np.abs(y + 40.0) > 8.0 + 2.5)
    assert np.percentile(err[sampled], 95) < 2.0
    assert 0.5 < field.coverage < 0.95
    band = np.abs(y + 40.0) < 8.0  # filled between data on both sides, 16 mm apart: harmonic, near the field
    assert err[band].mean() < 3.0 and np.percentile(err[band], 95) < 10.0
    # NIfTI's own order, under its SYMMATRIX intent, gives the same field
    lower = np.stack([d[:, i, j] for i, j in fr.NIFTI_ORDER], axis=-1).reshape(*shape, 6)
    again, _ = fiberdata.make(ta, fr.Source(nifti(tmp_path / "lower.nii.gz", lower, affine, intent="symmetric matrix"),
                                            min_fa=0.2))
    assert np.abs(again.x.array - a0.x.array).max() < 1e-6


def streamlines(step_mm=1.0, spacing_mm=2.0, length_mm=12.0, every_mm=10.0):
    """Polylines (points mm, offsets) along the synthetic field (midpoint steps), seeded on a
    grid across the TA every ``every_mm`` along it: short fascicle-like lines, which leave
    no gap at the central aponeurosis, away from which the field turns."""
    centre, axes = frame()
    local = (synthetic.nodes_mm() - centre) @ axes.T
    lo, hi = local.min(axis=0), local.max(axis=0)
    s, u, w = np.meshgrid(np.arange(lo[0], hi[0], every_mm), np.arange(lo[1], hi[1], spacing_mm),
                          np.arange(lo[2], hi[2], spacing_mm), indexing="ij")
    p = [centre + np.column_stack([s.ravel(), u.ravel(), w.ravel()]) @ axes]
    for _ in range(int(length_mm / step_mm)):
        half = p[-1] + 0.5 * step_mm * synthetic.field(p[-1])
        p.append(p[-1] + step_mm * synthetic.field(half))
    lines = np.stack(p, axis=1)  # (lines, points, 3)
    return lines.reshape(-1, 3), np.arange(0, lines.shape[0] * lines.shape[1] + 1, lines.shape[1])


def write_legacy(path, points, offsets, binary=False, new=False):
    counts = np.diff(offsets)
    head = f"# vtk DataFile Version {'5.1' if new else '3.0'}\nstreamlines\n{'BINARY' if binary else 'ASCII'}\n" \
           f"DATASET POLYDATA\nPOINTS {len(points)} float\n"
    with open(path, "wb") as f:
        f.write(head.encode())
        if binary:
            f.write(points.astype(">f4").tobytes() + b"\n")
        else:
            f.write("\n".join(" ".join(f"{v:.9g}" for v in p) for p in points).encode() + b"\n")
        conn = np.arange(len(points))
        if new:
            f.write(f"LINES {len(offsets)} {len(points)}\nOFFSETS vtktypeint64\n".encode())
            f.write(offsets.astype(">i8").tobytes() if binary else " ".join(map(str, offsets)).encode() + b"\n")
            f.write(b"\nCONNECTIVITY vtktypeint64\n")
            f.write(conn.astype(">i8").tobytes() if binary else " ".join(map(str, conn)).encode() + b"\n")
        else:
            cells = np.concatenate([np.r_[c, conn[o:o + c]] for o, c in zip(offsets[:-1], counts)])
            f.write(f"LINES {len(counts)} {len(cells)}\n".encode())
            f.write(cells.astype(">i4").tobytes() if binary else " ".join(map(str, cells)).encode() + b"\n")


def write_vtp(path, points, offsets, appended=False):
    """VTK XML PolyData: ascii arrays, or appended raw zlib-compressed ones (VTK's default)."""
    arrays = {"Points": points.astype("<f4").ravel(), "connectivity": np.arange(len(points), dtype="<i8"),
              "offsets": offsets[1:].astype("<i8")}
    kinds = {"Points": "Float32", "connectivity": "Int64", "offsets": "Int64"}
    blob, xml = b"", {}

    def opening(name):
        return f'<DataArray type="{kinds[name]}" Name="{name}" NumberOfComponents="{3 if name == "Points" else 1}"'

    for name, values in arrays.items():
        if appended:
            data = zlib.compress(values.tobytes())
            head = np.array([1, values.nbytes, values.nbytes, len(data)], dtype="<u8")
            xml[name] = f'{opening(name)} format="appended" offset="{len(blob)}"/>'
            blob += head.tobytes() + data
        else:
            xml[name] = f'{opening(name)} format="ascii">{" ".join(map(str, values))}</DataArray>'
    text = (f'<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" '
            f'header_type="UInt64"{" compressor=\"vtkZLibDataCompressor\"" if appended else ""}>\n<PolyData>\n'
            f'<Piece NumberOfPoints="{len(points)}" NumberOfLines="{len(offsets) - 1}">\n'
            f'<Points>{xml["Points"]}</Points>\n<Lines>{xml["connectivity"]}{xml["offsets"]}</Lines>\n'
            '</Piece>\n</PolyData>\n')
    tail = (b'<AppendedData encoding="raw">\n_' + blob + b"\n</AppendedData>\n") if appended else b""
    Path(path).write_bytes(text.encode() + tail + b"</VTKFile>\n")


@pytest.fixture(scope="module")
def lines():
    return streamlines()


def test_streamlines_in_every_format_give_the_same_field_near_the_known_one(ta, lines, tmp_path):
    points, offsets = lines
    np.savez(tmp_path / "lines.npz", points=points, offsets=offsets)
    a0, field = fiberdata.make(ta, fr.Source(tmp_path / "lines.npz"))
    err = errors(a0, synthetic.field)
    assert np.percentile(err, 95) < 2.0 and field.coverage > 0.95
    files = {"ascii.vtk": lambda p: write_legacy(p, points, offsets),
             "binary.vtk": lambda p: write_legacy(p, points, offsets, binary=True),
             "new_ascii.vtk": lambda p: write_legacy(p, points, offsets, new=True),
             "new_binary.vtk": lambda p: write_legacy(p, points, offsets, binary=True, new=True),
             "ascii.vtp": lambda p: write_vtp(p, points, offsets),
             "appended.vtp": lambda p: write_vtp(p, points, offsets, appended=True)}
    for name, write in files.items():
        write(tmp_path / name)
        other, _ = fiberdata.make(ta, fr.Source(tmp_path / name))
        # float32 points in the files (the npz holds float64)
        assert np.abs(other.x.array - a0.x.array).max() < 1e-4, name


def test_an_inline_zlib_array_decodes_as_vtk_writes_it(tmp_path):
    """meshio writes VTK XML arrays inline, base64, zlib-compressed: the decoder reads its points."""
    import xml.etree.ElementTree as ET

    import meshio

    points = np.random.default_rng(0).random((50, 3))
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(points, [("line", np.c_[np.arange(49), np.arange(1, 50)])]),
                 binary=True, compression="zlib")
    root = ET.parse(tmp_path / "m.vtu").getroot()
    header = {"byte_order": root.get("byte_order"), "header_type": {"UInt32": "u4", "UInt64": "u8"}[
        root.get("header_type", "UInt32")], "compressor": root.get("compressor"), "encoding": "raw"}
    assert header["compressor"] == "vtkZLibDataCompressor"
    element = root.find(".//Points/DataArray")
    assert np.array_equal(fr.xml_array(element, header, b"", tmp_path / "m.vtu").reshape(-1, 3), points)


def test_a_point_cloud_in_csv_and_npz_with_random_signs(ta, tmp_path):
    rng = np.random.default_rng(2)
    x = synthetic.nodes_mm()
    cloud = x.min(axis=0) + rng.random((20000, 3)) * np.ptp(x, axis=0)
    a = fanning(cloud) * rng.choice([-1.0, 1.0], size=(len(cloud), 1)) * rng.uniform(0.5, 2, (len(cloud), 1))
    table = np.column_stack([cloud, a])
    np.savetxt(tmp_path / "cloud.csv", table, delimiter=",", header="x,y,z,ax,ay,az", comments="")
    np.savez(tmp_path / "cloud.npz", **dict(zip(fr.CLOUD_KEYS, table.T)))
    a0, field = fiberdata.make(ta, fr.Source(tmp_path / "cloud.csv"))
    err = errors(a0, fanning)
    assert np.percentile(err, 95) < 2.0
    assert "point cloud (20000 points, unit mm), orientation tensors within 6.13 mm" in field.reader
    again, _ = fiberdata.make(ta, fr.Source(tmp_path / "cloud.npz"))
    assert np.abs(again.x.array - a0.x.array).max() < 1e-12
    # in metres, declared
    np.savetxt(tmp_path / "m.csv", np.column_stack([cloud * 1e-3, a]), delimiter=",", header="x,y,z,ax,ay,az",
               comments="")
    metres, _ = fiberdata.make(ta, fr.Source(tmp_path / "m.csv", unit="m"))
    assert np.abs(metres.x.array - a0.x.array).max() < 1e-9


def test_a_fibre_file_is_stored_and_read_back(ta, tmp_path):
    pytest.importorskip("nibabel")
    source = fr.Source(IMAGE)
    a0, field = fiberdata.make(ta, source)
    fiberdata.store(tmp_path / "f.h5", ta, a0, field, source, "0" * 64)
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert f.attrs["kind"] == "data" and f.attrs["coverage"] == 1.0 and f.attrs["source_sha256"] == "0" * 64
    assert np.array_equal(fibers.load(ta, tmp_path / "f.h5").x.array, a0.x.array)
    again, read = fiberdata.make(ta, fr.Source(tmp_path / "f.h5"))
    assert np.array_equal(again.x.array, a0.x.array) and read.coverage == 1.0
    assert fr.stored_fibres(tmp_path / "f.h5")[0] == "data"


def test_the_angle_against_the_stokes_fibres_is_reported(ta):
    pytest.importorskip("nibabel")
    stokes, note = fiberdata.stokes_beside(ta, fibers.fiber_path(NAME, kind="stokes"))
    assert note == ""
    a0, field = fiberdata.make(ta, fr.Source(IMAGE), stokes)
    exact = fiberdata.angles(nodal(a0)[1], nodal(stokes)[1])
    assert field.report["against_stokes"]["mean_deg"] == pytest.approx(exact.mean())
    assert field.report["against_stokes"]["p95_deg"] == pytest.approx(np.percentile(exact, 95))
    assert "against the Stokes fibres mean" in fiberdata.summary(field)


# ---------------------------------------------------------------------- bad input


def refused(ta, source_or_path, match):
    source = source_or_path if isinstance(source_or_path, fr.Source) else fr.Source(source_or_path)
    with pytest.raises(InputError, match=match):
        fiberdata.make(ta, source)


def test_malformed_images_are_refused(ta, tmp_path):
    pytest.importorskip("nibabel")
    world, shape, affine = grid(5.0)
    a = synthetic.field(world).reshape(*shape, 3)
    refused(ta, nifti(tmp_path / "3d.nii", a[..., 0], affine), r"expected a 4-D image with 3 \(eigenvector\) or 6")
    refused(ta, nifti(tmp_path / "4.nii", np.concatenate([a, a[..., :1]], axis=-1), affine), r"got shape \(.*, 4\)")
    nan = a.copy()
    nan[0, 0, 0, 0] = np.nan
    refused(ta, nifti(tmp_path / "nan.nii", nan, affine), "1 NaN or infinite value")
    refused(ta, nifti(tmp_path / "zero.nii", 0 * a, affine), "every voxel is zero: no tissue")
    # the mm grid with a header that says m
    refused(ta, nifti(tmp_path / "unit.nii", a, affine, unit="meter"),
            r"does not overlap the mesh's .* m: is the unit mm")
    shifted = affine.copy()
    shifted[:3, 3] += 500.0
    refused(ta, nifti(tmp_path / "frame.nii", a, shifted), "another frame")
    (tmp_path / "broken.nii.gz").write_bytes(b"not an image")
    refused(ta, tmp_path / "broken.nii.gz", "not a readable NIfTI image")


def test_malformed_samples_are_refused(ta, tmp_path):
    x = synthetic.nodes_mm()[:100]
    good = np.column_stack([x, np.tile([0.0, 0.0, 1.0], (100, 1))])
    rows = good.copy()
    rows[3, 3:] = 0.0
    np.savetxt(tmp_path / "zero.csv", rows, delimiter=",", header="x,y,z,ax,ay,az", comments="")
    refused(ta, tmp_path / "zero.csv", r"1 zero vector\(s\) \(point 3 the first\)")
    rows[3, 3:] = np.nan
    np.savetxt(tmp_path / "nan.csv", rows, delimiter=",", header="x,y,z,ax,ay,az", comments="")
    refused(ta, tmp_path / "nan.csv", "NaN or infinite")
    np.savetxt(tmp_path / "header.csv", good, delimiter=",", header="x,y,z,u,v,w", comments="")
    refused(ta, tmp_path / "header.csv", "missing ax, ay, az")
    np.savetxt(tmp_path / "m.csv", good, delimiter=",", header="x,y,z,ax,ay,az", comments="")
    refused(ta, fr.Source(tmp_path / "m.csv", unit="m"), r"is the unit mm\?")
    np.savez(tmp_path / "keys.npz", a=np.ones(3))
    refused(ta, tmp_path / "keys.npz", "expected the arrays points and offsets")
    np.savez(tmp_path / "offsets.npz", points=np.ones((5, 3)), offsets=np.array([0, 1, 5]))
    refused(ta, tmp_path / "offsets.npz", "at least two points a line")
    np.savez(tmp_path / "shape.npz", points=np.ones((5, 2)), offsets=np.array([0, 5]))
    refused(ta, tmp_path / "shape.npz", r"shape \(P, 3\), got \(5, 2\)")
    (tmp_path / "mesh.vtk").write_text("# vtk DataFile Version 3.0\nx\nASCII\nDATASET UNSTRUCTURED_GRID\n")
    refused(ta, tmp_path / "mesh.vtk", "expected DATASET POLYDATA")
    (tmp_path / "grid.vtp").write_text('<VTKFile type="UnstructuredGrid"></VTKFile>')
    refused(ta, tmp_path / "grid.vtp", "expected a VTK XML PolyData file")
    with pytest.raises(InputError, match="unknown fibre data format '.txt'"):
        fr.Source(tmp_path / "fibres.txt")
    with pytest.raises(InputError, match="no such file"):
        fr.Source(tmp_path / "missing.nii.gz")


def test_little_overlap_is_refused(ta, tmp_path):
    x = synthetic.nodes_mm()
    centre, (e1, _, _) = frame()
    tip = x[(x - centre) @ e1 > np.percentile((x - centre) @ e1, 97)]
    np.savetxt(tmp_path / "tip.csv", np.column_stack([tip, np.tile(e1, (len(tip), 1))]), delimiter=",",
               header="x,y,z,ax,ay,az", comments="")
    refused(ta, fr.Source(tmp_path / "tip.csv", radius=1e-3), r"only .* % of the mesh's nodes have data")


def test_the_jobs_refuse_bad_data_with_one_line_and_write_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    (tmp_path / "f.txt").write_text("")
    assert fibers_job.main(["--geometries", NAME, "--fibers", str(tmp_path / "f.txt"), "--output", str(out)]) == 2
    assert "expected a fibre data file (.nii" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z,ax,ay,az\n0,0,0,0,0,0\n")
    assert fibers_job.main(["--geometries", NAME, "--fibers", str(bad), "--output", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "zero vector" in err[0]
    assert not out.exists() or not any(out.iterdir())
    assert grow.main(["--geometry", NAME, "--fibers", "stokz", "--output", str(tmp_path / "g.h5")]) == 2
    assert "--fibers stokz: expected one of auto, original" in capsys.readouterr().err
    assert grow.main(["--geometry", NAME, "--fibers-unit", "m", "--output", str(tmp_path / "g.h5")]) == 2
    assert "--fibers-unit applies to --fibers FILE" in capsys.readouterr().err
    assert cohort_job.main(["--geometries", NAME, "TA_VHF_Left", "--fibers", str(bad), "--output", str(out)]) == 2
    assert "{geometry}" in capsys.readouterr().err
    assert contraction_job.main(["--fibers", str(tmp_path / "f.txt"), "--output", str(tmp_path / "c.h5")]) == 2
    assert "expected one of auto, idealized" in capsys.readouterr().err
    assert not (tmp_path / "g.h5").exists() and not (tmp_path / "c.h5").exists()


# ------------------------------------------------------------------- jobs and runs


def test_hyper_fibers_writes_a_fibre_file_and_a_picture(tmp_path):
    pytest.importorskip("nibabel")
    assert fibers_job.main(["--geometries", NAME, "--fibers", str(IMAGE), "--output", str(tmp_path), "--quiet"]) == 0
    out = tmp_path / f"{NAME}_fibers.h5"
    with h5py.File(out, "r") as f:
        assert f.attrs["kind"] == "data" and f.attrs["source_sha256"] == ckpt.file_digest(IMAGE)
        assert 17 < f.attrs["pennation_mean_deg"] < 20 and f.attrs["against_stokes_mean_deg"] > 10
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_a_run_records_its_fibres_from_data(tmp_path, capsys):
    pytest.importorskip("nibabel")
    protocol = tmp_path / "short.toml"
    protocol.write_text('name = "short"\nend = 24.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n')
    out = tmp_path / "ta.h5"
    assert grow.main(["--geometry", NAME, "--fibers", str(IMAGE), "--protocol", str(protocol), "--growth-dt", "24",
                      "--output", str(out), "--quiet"]) == 0
    with h5py.File(out, "r") as f:
        assert f.attrs["fibers"] == "data" and f.attrs["fibers_sha256"] == ckpt.file_digest(IMAGE)
        assert "NIfTI vector image" in f.attrs["fibers_method"] and "coverage 100.0 %" in f.attrs["fibers_method"]
        assert f"--fibers {IMAGE.resolve()}" in f.attrs["study"]
    assert inspect_job.main([str(out)]) == 0
    assert "fibres: data, from data: NIfTI vector image" in capsys.readouterr().out
    # another threshold is another run
    options = ["--geometry", NAME, "--fibers", str(IMAGE), "--protocol", str(protocol)]
    spec = grow.plan(MPI.COMM_SELF, options).specs[0]
    other = grow.plan(MPI.COMM_SELF, [*options, "--fibers-min-fa", "0.3"]).specs[0]
    assert spec.digest() != other.digest() and spec.fiber_data.min_fa == 0.1


def test_hyper_mesh_keeps_the_fibres_from_data_which_runs_then_use(tmp_path):
    pytest.importorskip("nibabel")
    out = tmp_path / "TA_DTI"
    stl = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"
    assert mesh_job.main([str(stl), "--output", str(out), "--cells", "3000", "--fibers", str(IMAGE), "--quiet"]) == 0
    record = json.loads((out / "mesh.json").read_text())["fibers_from_data"]
    assert record["source_sha256"] == ckpt.file_digest(IMAGE) and record["coverage"] > 0.8
    assert isinstance(record["against_stokes"], dict) and (out / "fibers.png").is_file()
    mesh = runspec.MeshFile(out / "TA_DTI.xdmf", "mm")
    spec = runspec.RunSpec("TA_DTI", protocols.from_option("mwf")[0], mesh=mesh)
    geometry = mesh.load(MPI.COMM_SELF)
    a0, record = driver.fiber_field(spec, geometry)
    assert record["fibers"] == "data" and record["fibers_method"].startswith("from data: NIfTI")
    assert np.array_equal(a0.x.array, fibers.load(geometry, out / "fibers.h5").x.array)


def test_a_study_mesh_takes_fibres_from_data(tmp_path):
    pytest.importorskip("nibabel")
    mesh = geo.MESHES_DIR / geo.GEOMETRIES[NAME]
    text = (f'protocols = ["mwf"]\n[[mesh]]\nfile = "{mesh}"\nunit = "mm"\nfibers = "{IMAGE}"\nfibers_min_fa = 0.2\n'
            'fibers_radius_mm = 4.0\n')
    (tmp_path / "s.toml").write_text(text)
    loaded = study.load(tmp_path / "s.toml")
    source = loaded.fibres[mesh.stem]
    assert source.path == IMAGE and source.min_fa == 0.2 and source.radius == pytest.approx(4e-3)
    settings, choice = study.steps(loaded)
    spec = study.first_spec(loaded, settings, choice)
    assert spec.fibers == "data" and spec.fiber_data == source
    assert 'fibers_min_fa = 0.2' in provenance.study_text(spec)
    (tmp_path / "bad.toml").write_text(text.replace(f'fibers = "{IMAGE}"\n', ""))
    with pytest.raises(InputError, match="fibers_min_fa applies to fibres from data"):
        study.load(tmp_path / "bad.toml")


# ---------------------------------------------------------------------- parallel


@pytest.mark.mpi
def test_two_ranks_equal_serial(tmp_path_factory):
    """The fibres on two ranks are those of one rank, bit for bit, at every node."""
    pytest.importorskip("nibabel")
    comm = MPI.COMM_WORLD
    folder = Path(comm.bcast(str(tmp_path_factory.mktemp("cloud")) if comm.rank == 0 else None))
    if comm.rank == 0:
        rng = np.random.default_rng(3)
        x = synthetic.nodes_mm()
        cloud = x.min(axis=0) + rng.random((5000, 3)) * np.ptp(x, axis=0)
        np.savetxt(folder / "c.csv", np.column_stack([cloud, synthetic.field(cloud)]), delimiter=",",
                   header="x,y,z,ax,ay,az", comments="")
    comm.barrier()
    for source in (fr.Source(IMAGE), fr.Source(folder / "c.csv")):
        parallel = geo.load(NAME, comm)
        a0, field = fiberdata.make(parallel, source)
        serial = geo.load(NAME, MPI.COMM_SELF)
        reference, ref_field = fiberdata.make(serial, source)
        keys = fibers.node_index(a0.function_space)
        ref_keys = fibers.node_index(reference.function_space)
        where = np.searchsorted(ref_keys[np.argsort(ref_keys)], keys)
        ref = reference.x.array.reshape(-1, 3)[np.argsort(ref_keys)][where]
        assert np.array_equal(a0.x.array.reshape(-1, 3), ref), np.abs(a0.x.array.reshape(-1, 3) - ref).max()
        assert field.report == ref_field.report, (field.report, ref_field.report)
