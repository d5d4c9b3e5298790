"""Fibre data files read into arrays (`hyper.fem.fiberdata` maps them onto a mesh): a DTI
image, tractography streamlines, a point cloud of vectors, or a hyper fibre file.
Every length is converted to metres here; every malformed file is an `InputError`
that says what is wrong with it.

Formats (docs/fibres-from-data.md has the details and examples):

- ``.nii``, ``.nii.gz``: a NIfTI image (nibabel), 4-D with 3 components per voxel (the
  primary eigenvector, e.g. FSL dtifit's ``_V1``) or 6 (the diffusion tensor). The 6
  components in FSL dtifit's order Dxx, Dxy, Dxz, Dyy, Dyz, Dzz, or, where the header's
  intent is NIfTI's SYMMATRIX (1005), in NIfTI's lower-triangle order Dxx, Dxy, Dyy, Dxz,
  Dyz, Dzz. A 5-D image with a 4th axis of length 1 (NIfTI's vector layout) is read as
  4-D. The affine (sform, else qform) maps voxel indices to world coordinates in the
  header's spatial unit (mm where the header does not say). Voxels whose vector or
  tensor is all zero are background (no tissue); NaN or infinite values are an error.
- ``.vtk`` (legacy, ASCII or BINARY, ``DATASET POLYDATA`` with ``POINTS`` and
  ``LINES``, the 4.x or the 5.1 layout) and ``.vtp`` (VTK XML PolyData: ascii, inline
  binary or appended raw data, uncompressed or zlib): streamlines, each a polyline.
- ``.npz`` with ``points`` (P, 3) and ``offsets`` (L + 1,): streamline l is
  points[offsets[l]:offsets[l + 1]], offsets[0] = 0, offsets[-1] = P, at least two
  points a line.
- ``.csv`` with a header x,y,z,ax,ay,az (other columns ignored), or ``.npz`` with those
  six keys, each of length n: a point cloud of vectors (their sign and length do not
  matter; a zero vector is an error).
- ``.h5``: a hyper fibre file (`hyper.fem.fibers.store`'s format) of this very mesh.
"""

from __future__ import annotations

import base64
import csv
import dataclasses
import re
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np

from hyper.core.io import reading_h5
from hyper.core.params import InputError, as_float

# what each suffix is read as
FORMATS = {".nii": "NIfTI image", ".nii.gz": "NIfTI image", ".vtk": "VTK legacy streamlines",
           ".vtp": "VTK XML streamlines", ".npz": "streamlines or point cloud (NumPy)",
           ".csv": "point cloud (CSV)", ".h5": "hyper fibre file"}
# metres per unit; auto: the NIfTI header's spatial unit, else mm (imaging's world unit)
UNITS = {"auto": None, "m": 1.0, "mm": 1.0e-3}
NIFTI_UNITS = {"meter": 1.0, "mm": 1.0e-3, "micron": 1.0e-6}
CLOUD_KEYS = ("x", "y", "z", "ax", "ay", "az")
# NIfTI's intent code of a symmetric matrix, stored as its lower triangle row by row
NIFTI_INTENT_SYMMATRIX = 1005
# (row, column) of each of the 6 stored tensor components
FSL_ORDER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
NIFTI_ORDER = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))
MIN_FA = 0.1  # below it a tensor voxel is too isotropic to give a direction (filled)


def suffix(path: Path) -> str:
    name = Path(path).name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else Path(name).suffix


@dataclasses.dataclass(frozen=True)
class Source:
    """A fibre data file and how to read it.

    unit: the file's length unit (`UNITS`); min_fa: the fractional-anisotropy threshold
    below which an image voxel has no direction (tensor images, or with ``fa``); radius
    (m): how far a streamline or cloud sample reaches a mesh node (None: 1.5 times the
    mesh's mean edge length); fa: a 3-D NIfTI image of fractional anisotropy on the
    grid of a vector image.
    """

    path: Path
    unit: str = "auto"
    min_fa: float = MIN_FA
    radius: float | None = None
    fa: Path | None = None

    def __post_init__(self):
        object.__setattr__(self, "path", Path(self.path))
        if suffix(self.path) not in FORMATS:
            raise InputError(f"{self.path}: unknown fibre data format {suffix(self.path)!r}; expected one of "
                             f"{', '.join(FORMATS)} (a NIfTI image, streamlines, a point cloud or a fibre file)")
        for path in (self.path, self.fa):
            if path is not None and not Path(path).is_file():
                raise InputError(f"{path}: no such file")
        if self.unit not in UNITS:
            raise InputError(f"fibre data unit: expected one of {', '.join(UNITS)}, got {self.unit!r}")
        as_float(self.min_fa, "fibre data min_fa", 0.0, below=1.0)
        if self.radius is not None:
            as_float(self.radius, "fibre data radius (m)", above=0.0)
        if self.fa is not None:
            object.__setattr__(self, "fa", Path(self.fa))
            if suffix(self.fa) not in (".nii", ".nii.gz") or suffix(self.path) not in (".nii", ".nii.gz"):
                raise InputError(f"{self.fa}: an FA image (NIfTI) goes with a NIfTI vector image")

    @property
    def format(self) -> str:
        return suffix(self.path)

    def attributes(self) -> dict:
        """The reading parameters, as a result records them."""
        out = {"file": str(self.path), "unit": self.unit, "min_fa": self.min_fa}
        if self.radius is not None:
            out["radius_m"] = self.radius
        if self.fa is not None:
            out["fa"] = str(self.fa)
        return out


@dataclasses.dataclass(frozen=True)
class Image:
    """A DTI image: ``values`` (X, Y, Z, 3 or 6), ``affine`` voxel index -> metres,
    ``order`` the tensor's components (6 only), ``fa`` (X, Y, Z) or None, ``unit`` the
    world unit it was given in (for messages)."""

    values: np.ndarray
    affine: np.ndarray
    order: tuple | None
    fa: np.ndarray | None
    unit: str

    @property
    def kind(self) -> str:
        return "tensor" if self.values.shape[-1] == 6 else "vector"

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounding box (m) of the centres of the voxels with tissue."""
        tissue = np.argwhere(np.any(self.values != 0, axis=-1))
        world = tissue @ self.affine[:3, :3].T + self.affine[:3, 3]
        return world.min(axis=0), world.max(axis=0)


@dataclasses.dataclass(frozen=True)
class Samples:
    """Directions at points (m): ``points`` (n, 3), unit ``directions`` (n, 3) and their
    ``weights`` (n,); streamlines as their pieces (midpoints, tangents, lengths)."""

    points: np.ndarray
    directions: np.ndarray
    weights: np.ndarray
    what: str  # "streamlines" or "point cloud"
    unit: str

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)


def scale(source: Source, header_unit: str | None = None) -> tuple[float, str]:
    """(metres per file unit, the unit's name)."""
    if source.unit != "auto":
        return UNITS[source.unit], source.unit
    if header_unit in NIFTI_UNITS:
        return NIFTI_UNITS[header_unit], {"meter": "m", "micron": "µm"}.get(header_unit, header_unit)
    return UNITS["mm"], "mm"


def finite(path: Path, what: str, values: np.ndarray) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} NaN or infinite value(s) in its {what}")


# ------------------------------------------------------------------------------ NIfTI


def read_nifti(path: Path, what: str = "image"):
    import nibabel

    try:
        image = nibabel.load(str(path))
        data = np.asarray(image.dataobj, dtype=np.float64)
    except (OSError, ValueError, EOFError, nibabel.filebasedimages.ImageFileError) as err:
        raise InputError(f"{path}: not a readable NIfTI {what} ({err})") from None
    return image, data


def read_image(source: Source) -> Image:
    path = source.path
    image, data = read_nifti(path)
    if data.ndim == 5 and data.shape[3] == 1:
        data = data[:, :, :, 0, :]
    if data.ndim != 4 or data.shape[-1] not in (3, 6):
        raise InputError(f"{path}: expected a 4-D image with 3 (eigenvector) or 6 (tensor) components per voxel, "
                         f"got shape {data.shape}")
    finite(path, "voxels", data)
    if not np.any(data != 0):
        raise InputError(f"{path}: every voxel is zero: no tissue")
    metres, unit = scale(source, image.header.get_xyzt_units()[0])
    affine = np.array(image.affine, dtype=float)
    if abs(np.linalg.det(affine[:3, :3])) == 0:
        raise InputError(f"{path}: its affine is singular")
    affine[:3] *= metres
    order = None
    if data.shape[-1] == 6:
        order = NIFTI_ORDER if int(image.header.get("intent_code", 0)) == NIFTI_INTENT_SYMMATRIX else FSL_ORDER
    fa = None
    if source.fa is not None:
        fa_image, fa = read_nifti(source.fa, "FA image")
        fa = np.squeeze(fa)
        if fa.shape != data.shape[:3] or not np.allclose(fa_image.affine, image.affine):
            raise InputError(f"{source.fa}: the FA image's grid {fa.shape} or affine is not the image's "
                             f"{data.shape[:3]}")
        finite(source.fa, "voxels", fa)
    return Image(data, affine, order, fa, unit)


def tensor_fa(tensors: np.ndarray) -> np.ndarray:
    """Fractional anisotropy of symmetric 3x3 tensors (..., 3, 3), by invariants:
    sqrt(3/2) |D - tr(D)/3 I| / |D| (0 for a zero tensor)."""
    trace = np.trace(tensors, axis1=-2, axis2=-1)
    deviator = tensors - trace[..., None, None] / 3.0 * np.eye(3)
    norm = np.linalg.norm(tensors, axis=(-2, -1))
    return np.sqrt(1.5) * np.linalg.norm(deviator, axis=(-2, -1)) / np.where(norm > 0, norm, 1.0)


def full_tensors(values: np.ndarray, order) -> np.ndarray:
    """(..., 6) stored components in ``order`` -> (..., 3, 3) symmetric tensors."""
    out = np.empty(values.shape[:-1] + (3, 3))
    for k, (i, j) in enumerate(order):
        out[..., i, j] = out[..., j, i] = values[..., k]
    return out


# ------------------------------------------------------------------------ streamlines


def pieces(points: np.ndarray, offsets: np.ndarray, path: Path, unit: str) -> Samples:
    """Every segment of every polyline: midpoint, unit tangent, length (its weight)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{path}: expected streamline points of shape (P, 3), got {points.shape}")
    finite(path, "points", points)
    if (offsets.ndim != 1 or len(offsets) < 2 or offsets[0] != 0 or offsets[-1] != len(points)
            or np.any(np.diff(offsets) < 2)):
        raise InputError(f"{path}: expected offsets (L + 1,) from 0 to the number of points ({len(points)}), "
                         "at least two points a line")
    segment = np.ones(len(points) - 1, dtype=bool)
    segment[offsets[1:-1] - 1] = False  # from a line's last point to the next line's first: no segment
    a, b = points[:-1][segment], points[1:][segment]
    length = np.linalg.norm(b - a, axis=1)
    if not np.any(length > 0):
        raise InputError(f"{path}: every streamline segment has zero length")
    keep = length > 0
    return Samples((a[keep] + b[keep]) / 2, (b[keep] - a[keep]) / length[keep, None], length[keep],
                   "streamlines", unit)


class LegacyVTK:
    """A cursor over a legacy VTK file: keyword lines, then ASCII or big-endian BINARY numbers."""

    TYPES = {"float": ">f4", "double": ">f8", "int": ">i4", "vtktypeint32": ">i4", "unsigned_int": ">u4",
             "long": ">i8", "vtktypeint64": ">i8", "vtkidtype": ">i8"}

    def __init__(self, path: Path):
        self.path = path
        self.body = path.read_bytes()
        head = self.body.split(b"\n", 4)
        if len(head) < 5 or not head[0].startswith(b"# vtk DataFile"):
            raise InputError(f"{path}: not a legacy VTK file (no '# vtk DataFile' header)")
        self.binary = head[2].strip().upper() == b"BINARY"
        if head[3].split()[-1:] != [b"POLYDATA"]:
            raise InputError(f"{path}: expected DATASET POLYDATA (streamlines), got "
                             f"{head[3].decode(errors='replace')!r}")
        self.position = sum(len(line) + 1 for line in head[:4])

    def line(self) -> list[bytes]:
        end = self.body.find(b"\n", self.position)
        end = len(self.body) if end < 0 else end
        words = self.body[self.position:end].split()
        self.position = end + 1
        return words

    def keyword(self) -> list[str] | None:
        """The next non-blank line's words, None at the end."""
        while self.position < len(self.body):
            words = self.line()
            if words:
                return [w.decode(errors="replace") for w in words]
        return None

    def numbers(self, count: int, kind: str) -> np.ndarray:
        if self.binary:
            dtype = np.dtype(self.TYPES.get(kind.lower(), ">f4"))
            values = np.frombuffer(self.body, dtype=dtype, count=count, offset=self.position)
            self.position += count * dtype.itemsize
            return values.astype(np.float64 if dtype.kind == "f" else np.int64)
        words = []
        while len(words) < count and self.position < len(self.body):
            words += self.line()
        if len(words) != count:
            raise InputError(f"{self.path}: expected {count} numbers, found {len(words)}")
        return np.array(words, dtype=np.float64)


def counted_cells(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connectivity and offsets of legacy 4.x cells, each its point count then its points."""
    counts, starts, k = [], [], 0
    while k < len(cells):
        starts.append(k + 1)
        counts.append(int(cells[k]))
        k += int(cells[k]) + 1
    connectivity = np.concatenate([cells[s:s + c] for s, c in zip(starts, counts)]) if counts else cells[:0]
    return connectivity, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def legacy_vtk(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Points and line offsets of a legacy VTK POLYDATA file (ASCII or BINARY, 4.x or 5.1)."""
    f = LegacyVTK(path)
    points = offsets = connectivity = None
    try:
        while (words := f.keyword()) is not None:
            head = words[0].upper()
            if head == "POINTS":
                points = f.numbers(3 * int(words[1]), words[2]).reshape(-1, 3)
            elif head == "LINES":
                n, size = int(words[1]), int(words[2])
                before = f.position
                following = f.keyword()
                if following is not None and following[0].upper() == "OFFSETS":  # the 5.1 layout
                    offsets = f.numbers(n, following[1]).astype(np.int64)
                    connectivity = f.numbers(size, f.keyword()[1]).astype(np.int64)
                else:
                    f.position = before
                    connectivity, offsets = counted_cells(f.numbers(size, "int").astype(np.int64))
            elif head in ("POINT_DATA", "CELL_DATA", "METADATA", "FIELD"):
                break
            elif head in ("VERTICES", "POLYGONS", "TRIANGLE_STRIPS"):
                raise InputError(f"{path}: holds {head.lower()}, not streamlines (LINES)")
    except (ValueError, IndexError, TypeError) as err:
        raise InputError(f"{path}: malformed legacy VTK file ({err})") from None
    if points is None or offsets is None:
        raise InputError(f"{path}: expected POINTS and LINES (streamlines)")
    if connectivity.size and (connectivity.min() < 0 or connectivity.max() >= len(points)):
        raise InputError(f"{path}: a line refers to a point that does not exist")
    return points[connectivity], offsets


def xml_array(element: ET.Element, header: dict, appended: bytes, path: Path) -> np.ndarray:
    """The values of one VTK XML DataArray (ascii, inline binary or appended raw)."""
    order = "<" if header["byte_order"] == "LittleEndian" else ">"
    kinds = {"Float32": "f4", "Float64": "f8", "Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2",
             "Int32": "i4", "UInt32": "u4", "Int64": "i8", "UInt64": "u8"}
    kind = element.get("type")
    if kind not in kinds:
        raise InputError(f"{path}: DataArray of unknown type {kind!r}")
    dtype = np.dtype(order + kinds[kind])
    size = np.dtype(order + header["header_type"])
    compressed = header["compressor"] is not None
    form = element.get("format", "ascii")
    if form == "ascii":
        return np.array((element.text or "").split(), dtype=dtype)
    if form == "binary":
        text = "".join((element.text or "").split()).encode()
        if not compressed:
            blob = base64.b64decode(text)
            count = int(np.frombuffer(blob, size, 1)[0])
            return np.frombuffer(blob, dtype, count // dtype.itemsize, size.itemsize)
        # zlib: the block header and the blocks are encoded separately
        first = base64.b64decode(text[:4 * ((3 * size.itemsize + 2) // 3)])
        blocks = int(np.frombuffer(first, size, 1)[0])
        length = 4 * (((3 + blocks) * size.itemsize + 2) // 3)
        head = np.frombuffer(base64.b64decode(text[:length]), size, 3 + blocks)
        return inflate(head, base64.b64decode(text[length:]), dtype)
    if form == "appended":
        offset = int(element.get("offset", 0))
        if header["encoding"] != "raw":
            raise InputError(f"{path}: appended data encoded as {header['encoding']!r}; expected raw (or save the "
                             "file with ascii or binary arrays)")
        if not compressed:
            count = int(np.frombuffer(appended, size, 1, offset)[0])
            return np.frombuffer(appended, dtype, count // dtype.itemsize, offset + size.itemsize)
        blocks = int(np.frombuffer(appended, size, 1, offset)[0])
        head = np.frombuffer(appended, size, 3 + blocks, offset)
        start = offset + (3 + blocks) * size.itemsize
        return inflate(head, appended[start:start + int(head[3:].sum())], dtype)
    raise InputError(f"{path}: DataArray format {form!r}; expected ascii, binary or appended")


def inflate(head: np.ndarray, data: bytes, dtype: np.dtype) -> np.ndarray:
    """zlib blocks of a VTK XML array: head = [blocks, block size, last block size, sizes…]."""
    out, start = [], 0
    for n in head[3:]:
        out.append(zlib.decompress(data[start:start + int(n)]))
        start += int(n)
    return np.frombuffer(b"".join(out), dtype)


def xml_vtk(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Points and line offsets of a VTK XML PolyData file."""
    raw = path.read_bytes()
    appended = b""
    at = raw.find(b"<AppendedData")
    if at >= 0:  # raw bytes follow '_': not XML, cut them off before parsing the rest
        start = raw.index(b"_", raw.index(b">", at)) + 1
        end = raw.rfind(b"</AppendedData>")
        appended = raw[start:end]
        encoding = re.search(rb'encoding="(\w+)"', raw[at:start])
        raw = raw[:at] + b"</VTKFile>"
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as err:
        raise InputError(f"{path}: not a readable VTK XML file ({err})") from None
    if root.tag != "VTKFile" or root.get("type") != "PolyData":
        raise InputError(f"{path}: expected a VTK XML PolyData file (streamlines), got "
                         f"{root.get('type')!r}")
    compressor = root.get("compressor")
    if compressor not in (None, "vtkZLibDataCompressor"):
        raise InputError(f"{path}: compressor {compressor}; expected none or vtkZLibDataCompressor")
    header = {"byte_order": root.get("byte_order", "LittleEndian"), "header_type": {"UInt32": "u4", "UInt64": "u8"}[
        root.get("header_type", "UInt32")], "compressor": compressor,
        "encoding": encoding.group(1).decode() if at >= 0 and encoding else "raw"}
    points, offsets, connectivity = [], [], []
    for piece in root.iter("Piece"):
        base = sum(len(p) for p in points)
        p = piece.find("Points/DataArray")
        lines = piece.find("Lines")
        if p is None or lines is None:
            raise InputError(f"{path}: a Piece without Points or Lines: no streamlines")
        arrays = {a.get("Name"): a for a in lines.iter("DataArray")}
        if "connectivity" not in arrays or "offsets" not in arrays:
            raise InputError(f"{path}: Lines without connectivity and offsets arrays")
        points.append(xml_array(p, header, appended, path).astype(float).reshape(-1, 3))
        connectivity.append(xml_array(arrays["connectivity"], header, appended, path).astype(np.int64) + base)
        ends = xml_array(arrays["offsets"], header, appended, path).astype(np.int64)
        offsets.append(ends + (offsets[-1][-1] if offsets else 0))
    if not points:
        raise InputError(f"{path}: no Piece: no streamlines")
    points, connectivity = np.concatenate(points), np.concatenate(connectivity)
    offsets = np.concatenate([[0], *offsets])
    if connectivity.size and (connectivity.min() < 0 or connectivity.max() >= len(points)):
        raise InputError(f"{path}: a line refers to a point that does not exist")
    return points[connectivity], offsets


# ------------------------------------------------------------------------ point clouds


def cloud(path: Path, columns: dict[str, np.ndarray], unit: str, metres: float) -> Samples:
    x = np.column_stack([np.asarray(columns[k], dtype=float).ravel() for k in CLOUD_KEYS[:3]])
    a = np.column_stack([np.asarray(columns[k], dtype=float).ravel() for k in CLOUD_KEYS[3:]])
    if len(x) == 0:
        raise InputError(f"{path}: no points")
    finite(path, "points or vectors", np.hstack([x, a]))
    length = np.linalg.norm(a, axis=1)
    zero = np.flatnonzero(length == 0)
    if zero.size:
        raise InputError(f"{path}: {zero.size} zero vector(s) (point {zero[0]} the first), which have no direction")
    return Samples(x * metres, a / length[:, None], np.ones(len(x)), "point cloud", unit)


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise InputError(f"{path}: empty")
    names = [h.strip().lower() for h in rows[0]]
    missing = [k for k in CLOUD_KEYS if k not in names]
    if missing:
        raise InputError(f"{path}: expected a header with columns {','.join(CLOUD_KEYS)}; missing {', '.join(missing)}")
    where = [names.index(k) for k in CLOUD_KEYS]
    try:
        values = np.array([[float(row[i]) for i in where] for row in rows[1:] if row], dtype=float).reshape(-1, 6)
    except (ValueError, IndexError) as err:
        raise InputError(f"{path}: a row is not six numbers under {','.join(CLOUD_KEYS)} ({err})") from None
    return dict(zip(CLOUD_KEYS, values.T))


def read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: not a readable .npz file ({err})") from None


def read_samples(source: Source) -> Samples:
    """Streamlines or a point cloud, in metres."""
    path = source.path
    metres, unit = scale(source)
    if source.format == ".csv":
        return cloud(path, read_csv(path), unit, metres)
    if source.format == ".npz":
        arrays = read_npz(path)
        if {"points", "offsets"} <= set(arrays):
            return pieces(np.asarray(arrays["points"], dtype=float) * metres, arrays["offsets"], path, unit)
        if set(CLOUD_KEYS) <= set(arrays):
            sizes = {np.asarray(arrays[k]).size for k in CLOUD_KEYS}
            if len(sizes) != 1:
                raise InputError(f"{path}: {','.join(CLOUD_KEYS)} have different lengths {sorted(sizes)}")
            return cloud(path, arrays, unit, metres)
        raise InputError(f"{path}: expected the arrays points and offsets (streamlines) or "
                         f"{', '.join(CLOUD_KEYS)} (a point cloud); it has {', '.join(arrays) or 'none'}")
    points, offsets = (legacy_vtk if source.format == ".vtk" else xml_vtk)(path)
    return pieces(points * metres, offsets, path, unit)


def stored_fibres(path: Path) -> tuple[str, str]:
    """(kind, method) a fibre file records: "data" (`hyper.fem.fiberdata.store`), "pennate"
    (`hyper.fem.pennate.store`); a file without a kind (`hyper.fem.fibers.store`'s, an older
    `hyper mesh`'s) holds Stokes fibres, made as its method says."""
    with reading_h5(path, "fibre file") as f:
        return str(f.attrs.get("kind", "stokes")), str(f.attrs.get("method", ""))
