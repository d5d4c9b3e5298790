# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""Experiment of issue 32 item 2 (docs/convergence.md, "Why the fibres change"). Run from the
repository root, 1 core:

    FC_WORK=results/fibreconv python jobs/fibreconv_build.py TA_VHF_Left \
        ../shared/surfaces/VHF_Left_Muscle_TibialisAnterior_smooth.stl 4000,8000,16000,32000,64000
    FC_WORK=results/fibreconv python jobs/fibreconv_exp.py TA_VHF_Left \
        ../shared/surfaces/VHF_Left_Muscle_TibialisAnterior_smooth.stl --cells 8000,16000,32000,64000 \
        [--rule band3|stl|stlv] [--filter MM] [--normals vertex|stl] [--sigma MM]

(GM_VHF_Left: its surface VHF_Left_Muscle_GastrocnemiusMedial_smooth.stl, and `0,0,1` as the
build's fourth argument, the origin's direction.) build: gmsh meshes as `hyper mesh` makes
them, with the vertex rule's tags; exp: re-tag (band3 the vertex rule, stlv the STL's axis
with all three vertices in the band, stl the STL's axis and extent with facet centroids),
solve the Stokes fibres, smooth them (--filter l, `fibers.smoothed`), and print the angle of
each level's field to the finest one at the level's nodes (mean, p95, max)."""
import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

WORK = os.environ.get('FC_WORK', 'results/fibreconv')
from hyper.commands import mesh as mj
from hyper.commands.bench import mesh as mb
from hyper.fem import meshing as hm

name, stl = sys.argv[1], sys.argv[2]
toward = mb.shipped(name)["toward"] if len(sys.argv) < 5 else np.array(list(map(float, sys.argv[4].split(","))))
for cells in map(int, sys.argv[3].split(",")):
    out = Path(f"{WORK}/{name}_{cells}.npz")
    if out.exists():
        continue
    t = time.perf_counter()
    b = mj.build(argparse.Namespace(surface=Path(stl), unit="mm", cells=cells, axis=None, gmsh_budget=None,
                                    end_band=hm.END_BAND, origin_toward=toward))
    Path(WORK).mkdir(parents=True, exist_ok=True)
    np.savez(out, x=b["x"], tets=b["tets"], facets=b["facets"], tags=b["tags"], toward=toward)
    print(name, cells, len(b["tets"]), b["end_area_mm2"], f"{time.perf_counter()-t:.0f}s", flush=True)
