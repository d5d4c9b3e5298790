"""``make demo``: the paper's idealized-muscle experiment (Fig. 3A–E and 4C–E analogs).

Runs the signaling model and the coupled growth model on the idealized fusiform muscle
for the three paper protocols (mwf, every3days, weekly), nine weeks each, at the default
accuracy, and prints where the figures, time series and ParaView files are.
Run it under MPI as well: ``mpirun -n 2 python -m hyper.demo``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mpi4py import MPI

from hyper import grow, signaling


def main(argv=None) -> int:
    comm = MPI.COMM_WORLD
    sig = Path("results/signaling")
    growth = Path("results/grow")
    rc = 0
    if comm.rank == 0:
        rc = signaling.main(["--protocol", "all", "--output", str(sig), "--plot", str(sig / "protocols.png")])
    rc = comm.bcast(rc, root=0)
    if rc == 0:
        rc = grow.main(["--geometry", "idealized", "--protocol", "all", "--output", str(growth)])
    if rc == 0 and comm.rank == 0:
        print("\ndemo done:")
        print(f"  signaling figure (Fig. 3A-E analog): {(sig / 'protocols.png').resolve()}")
        print(f"  growth figure (Fig. 4C-E analog):    {(growth / 'idealized_growth.png').resolve()}")
        print(f"  time series (HDF5):                  {growth.resolve()}/idealized_<protocol>.h5")
        print(f"  ParaView (open with the XDMF3 reader): {growth.resolve()}/idealized_<protocol>_fields.xdmf")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
