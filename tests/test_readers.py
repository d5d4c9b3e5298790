"""The readers every job reads its inputs through (issue 37), tested as mechanisms:

- `hyper.core.params.read_text`: a text input (CSV, TOML, XDMF, template) is strict UTF-8;
  binary, UTF-16 and stray bytes are one InputError naming the file and the byte offset.
- `hyper.core.io.reading_h5`, `read_xml`: a result or field file that HDF5 or XML cannot
  read (damaged inside, truncated, no <Time>) is one InputError naming the file.
- `hyper.commands.cli.entry`: a closed pipe on stdout ends a job as SIGPIPE ends a Unix
  tool (exit 141, nothing on stderr).
- `hyper.fem.mechanics.refused`: PETSc's refusal names the options as the job took them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from hyper.commands import cli
from hyper.core import io
from hyper.core.params import InputError, read_text, read_toml
from hyper.runs import checkpoint as ckpt
from hyper.runs import measured

ROOT = Path(__file__).resolve().parents[1]
CSV = "week,csa\n0,10.0\n3,10.5\n"


# ---------------------------------------------------------------------- text inputs


@pytest.mark.parametrize("data, message", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", r"b.txt: not text: a NUL byte at byte offset 8"),
    ("week,csa\n0,1\n".encode("utf-16"), r"b.txt: UTF-16 text \(a byte order mark at byte 0\); save it as UTF-8"),
    ("week,csa\n".encode("utf-16-be"), r"b.txt: not text: a NUL byte at byte offset 0"),
    ("week\n".encode("utf-32"), r"b.txt: UTF-32 text"),
    (b"week,csa\n0,1\x00\n", r"b.txt: not text: a NUL byte at byte offset 12"),
    ("week,caf\u00e9\n".encode("latin-1"), r"b.txt: not UTF-8 text: byte 0xe9 at byte offset 8 \(invalid"),
    (b"\xef\xbb\xbfweek,\xff\n", r"b.txt: not UTF-8 text: byte 0xff at byte offset 8"),  # the BOM counts
])
def test_text_that_is_not_utf8_is_refused_with_the_file_and_the_byte_offset(tmp_path, data, message):
    (tmp_path / "b.txt").write_bytes(data)
    with pytest.raises(InputError, match=message):
        read_text(tmp_path / "b.txt")


def test_utf8_text_is_read_as_it_is_and_its_byte_order_mark_dropped(tmp_path):
    (tmp_path / "plain.csv").write_text("week,csa\n0,caf\u00e9\n", encoding="utf-8")
    (tmp_path / "marked.csv").write_bytes(b"\xef\xbb\xbf" + "week,csa\n0,caf\u00e9\n".encode())
    assert read_text(tmp_path / "plain.csv") == read_text(tmp_path / "marked.csv") == "week,csa\n0,caf\u00e9\n"


def test_a_folder_or_no_file_is_refused(tmp_path):
    with pytest.raises(InputError, match=r"x.csv: is a folder, not a CSV file"):
        (tmp_path / "x.csv").mkdir()
        read_text(tmp_path / "x.csv", "CSV file")
    with pytest.raises(InputError, match=r"none.csv: no such file"):
        read_text(tmp_path / "none.csv")


def test_the_readers_of_text_inputs_use_it(tmp_path):
    """A data CSV and a TOML file, each as a spreadsheet writes it (UTF-8 with a BOM) and as
    a UTF-16 export."""
    (tmp_path / "marked.csv").write_bytes(b"\xef\xbb\xbf" + CSV.encode())
    (tmp_path / "wide.csv").write_bytes(CSV.encode("utf-16"))
    assert measured.read(tmp_path / "marked.csv").csa_ratio.tolist() == [1.05]  # 'week', not '\ufeffweek'
    with pytest.raises(InputError, match=r"wide.csv: UTF-16 text"):
        measured.read(tmp_path / "wide.csv")
    (tmp_path / "marked.toml").write_bytes(b"\xef\xbb\xbfkM = 0.01\n")
    (tmp_path / "wide.toml").write_bytes("kM = 0.01\n".encode("utf-16"))
    assert read_toml(tmp_path / "marked.toml") == {"kM": 0.01}
    with pytest.raises(InputError, match=r"wide.toml: UTF-16 text"):
        read_toml(tmp_path / "wide.toml")


# --------------------------------------------------------------- results and fields


@pytest.fixture
def result(tmp_path) -> Path:
    return io.write_series(tmp_path / "r.h5", {"t": np.arange(2000.0), "csa_ratio": np.ones(2000)},
                           attrs={"geometry": "cylinder"}, groups={"protocol": {"name": "mwf"}})


def damaged(path: Path) -> Path:
    """``path`` with its middle (the object headers, past the superblock) zeroed, its size kept."""
    data = bytearray(path.read_bytes())
    data[800:len(data) - 100] = bytes(len(data) - 900)
    out = path.with_name("damaged.h5")
    out.write_bytes(bytes(data))
    return out


def truncated(path: Path) -> Path:
    out = path.with_name("truncated.h5")
    out.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return out


@pytest.mark.parametrize("spoil, message", [
    (damaged, r"damaged.h5: not a readable HDF5 result file \(.*\)"),
    (truncated, r"truncated.h5: not a readable HDF5 result file \(.*truncated file"),
    (lambda p: p.with_name("text.h5").write_text("t,csa\n") and p.with_name("text.h5"),
     r"text.h5: not a readable HDF5 result file \(.*signature"),
])
def test_a_damaged_result_is_an_input_error_naming_the_file(result, spoil, message):
    bad = spoil(result)
    assert bad.stat().st_size > 0
    with pytest.raises(InputError, match=message):
        with io.reading_h5(bad) as f:
            {k: f[k][()] for k in f}
    if spoil is damaged:  # the superblock is whole: the damage shows only inside
        assert bad.stat().st_size == result.stat().st_size
    assert not io.is_complete(bad)  # what a resuming job asks first: no traceback either


def test_what_the_block_reads_is_checked_too(result):
    with pytest.raises(InputError, match=r"r.h5: not a readable HDF5 result file \(.*'absent'"):
        with io.reading_h5(result) as f:
            f["absent"][()]
    with pytest.raises(InputError, match=r"^mine$"):  # the block's own InputErrors pass as they are
        with io.reading_h5(result):
            raise InputError("mine")
    with pytest.raises(InputError, match=r"r.h5: is a folder, not an HDF5 result file"):
        result.unlink()
        result.mkdir()
        with io.reading_h5(result):
            pass


def test_a_damaged_checkpoint_is_refused_with_the_way_out(tmp_path, result):
    with pytest.raises(InputError, match=r"damaged.h5: not a readable checkpoint .*; remove it or pass --restart"):
        ckpt.inspect(damaged(result), "0" * 64)
    assert io.is_complete(result) and not io.is_complete(damaged(result))


FIELDS = """<?xml version="1.0"?>
<Xdmf Version="3.0"><Domain><Grid Name="fields" GridType="Collection" CollectionType="Temporal">
<Grid Name="fields" GridType="Uniform">
  <Geometry GeometryType="XYZ"><DataItem Dimensions="2 3" Format="HDF">f.h5:/x</DataItem></Geometry>
  {time}
  <Attribute Name="u" AttributeType="Vector" Center="Node">{item}</Attribute>
</Grid></Grid></Domain></Xdmf>
"""
TIME = '<Time Value="24" />'
ITEM = '<DataItem Dimensions="2 3" Format="HDF">f.h5:/u</DataItem>'


@pytest.fixture
def fields(tmp_path) -> Path:
    with h5py.File(tmp_path / "f.h5", "w") as f:
        f["x"] = np.eye(2, 3)
        f["u"] = np.ones((2, 3))
    return tmp_path / "f.xdmf"


def test_a_field_file_is_read(fields):
    fields.write_text(FIELDS.format(time=TIME, item=ITEM))
    nodes, snapshots = io.read_point_field(fields, "u")
    assert nodes.shape == (2, 3) and [t for t, _ in snapshots] == [24.0]


@pytest.mark.parametrize("text, message", [
    (FIELDS.format(time="", item=ITEM), r"f.xdmf: a <Grid> without <Time>"),
    (FIELDS.format(time="<Time />", item=ITEM), r"f.xdmf: a <Time> without its Value attribute"),
    (FIELDS.format(time='<Time Value="noon" />', item=ITEM), r"f.xdmf: a <Time> whose Value is not a number"),
    (FIELDS.format(time=TIME, item=""), r"f.xdmf: a <Attribute> without <DataItem>"),
    (FIELDS.format(time=TIME, item='<DataItem Format="HDF">/u</DataItem>'), r"names no FILE.h5:DATASET"),
    (FIELDS.format(time=TIME, item='<DataItem Format="HDF">f.h5:/v</DataItem>'),
     r"f.xdmf: cannot read f.h5:/v: .*f.h5: not a readable HDF5 data file"),
    (FIELDS.format(time=TIME, item=ITEM)[:-40], r"f.xdmf: not a well-formed XDMF file \(.*line"),
    (b"\x89HDF\r\n\x1a\n\x00\x00", r"f.xdmf: not text: a NUL byte at byte offset 8"),
])
def test_a_malformed_field_file_is_an_input_error_naming_the_file(fields, text, message):
    if isinstance(text, bytes):
        fields.write_bytes(text)
    else:
        fields.write_text(text)
    with pytest.raises(InputError, match=message):
        io.read_point_field(fields, "u")


# ---------------------------------------------------------------------- closed pipes


def test_a_closed_pipe_is_told_from_an_open_one():
    for close_reader, gone in ((True, True), (False, False)):
        r, w = os.pipe()
        if close_reader:
            os.close(r)
        code = "import sys; from hyper.commands import cli; sys.exit(0 if cli.stdout_reader_gone() else 1)"
        done = subprocess.run([sys.executable, "-c", code], stdout=w, cwd=ROOT, timeout=60)
        os.close(w)
        if not close_reader:
            os.close(r)
        assert (done.returncode == 0) == gone


def closed_pipe(*argv) -> subprocess.CompletedProcess:
    """``python -m hyper.JOB ARGV | head -0``, without its race: the reader is gone before the
    job writes (head -0 may exit after a short output fitted in the pipe)."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run([sys.executable, "-m", *argv], stdout=w, stderr=subprocess.PIPE, text=True,
                              cwd=ROOT, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    finally:
        os.close(w)


def test_inspect_into_a_closed_pipe_ends_as_unix_tools_do(result):
    done = closed_pipe("hyper.inspect", str(result))
    assert (done.returncode, done.stderr) == (cli.EXIT_PIPE, "")


def test_slurm_into_a_closed_pipe_ends_as_unix_tools_do(tmp_path):
    """hyper slurm starts PETSc, whose own SIGPIPE handler aborted with a page of errors."""
    done = closed_pipe("hyper.slurm", "cohort", "--workdir", str(tmp_path))
    assert (done.returncode, done.stderr) == (cli.EXIT_PIPE, "")


def test_a_broken_pipe_elsewhere_is_a_failure(capsys):
    """Only stdout's closed pipe ends a job quietly; a BrokenPipeError from another pipe is raised."""
    def run(comm, args):
        raise BrokenPipeError("a subprocess's pipe")

    main = cli.entry(lambda: cli.Parser("test"), run, world=False)
    with pytest.raises(BrokenPipeError):
        main([])


# ------------------------------------------------------------------ PETSc's refusal


class Options:
    """A stand-in for PETSc's options database."""

    def __init__(self, values):
        self.values = values

    def getAll(self):
        return dict(self.values)


def test_petsc_refusal_names_the_options_as_the_job_took_them():
    from hyper.fem.mechanics import refused

    # grow: --petsc-option, each KEY=VALUE; the job's own defaults are not the user's
    db = Options({"mechanics_snes_type": "bogus", "mechanics_ksp_type": "preonly"})
    assert refused(db, "mechanics_", {"snes_type": "bogus", "ksp_type": "preonly"}, ("snes_type",),
                   ["mechanics_snes_type", "mechanics_ksp_type"]) == "--petsc-option snes_type=bogus"
    # contraction: its command line's -mechanics_ words, a flag without a value
    db = Options({"mechanics_snes_type": "bogus", "mechanics_ksp_monitor": None, "mechanics_ksp_type": "preonly",
                  "other_snes_type": "x"})
    assert refused(db, "mechanics_", {"ksp_type": "preonly"}, (), ["mechanics_ksp_type"]) == \
        "-mechanics_ksp_monitor, -mechanics_snes_type bogus"
    # none of the user's: never a blank
    assert "default options" in refused(Options({}), "mechanics_", {}, (), [])
