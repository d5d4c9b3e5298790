"""hyper demo (``make demo``): the paper's idealized-muscle experiment (Fig. 3A–E and 4C–E analogs).

Runs the signaling model and the coupled growth model on the idealized fusiform muscle
for the three paper protocols (mwf, every3days, weekly), nine weeks each, at the default
accuracy, and says where the figures, time series and ParaView files are.
Run it under MPI as well: ``mpirun -n 2 python -m hyper.demo``.
"""

from __future__ import annotations

import sys

from hyper.commands import cli
from hyper.core import log


def parser() -> cli.Parser:
    p = cli.Parser("demo", description=__doc__)
    p.add_argument("--output", type=cli.output(folder=True), default="results",
                   help="folder that gets signaling/ and grow/ with the results")
    return p


def run(comm, args) -> int:
    sig = args.output / "signaling"
    growth = args.output / "grow"
    rc = cli.main(["signaling", "--protocol", "all", "--output", str(sig), "--plot", str(sig / "protocols.png")])
    if rc == cli.EXIT_OK:
        rc = cli.main(["grow", "--geometry", "idealized", "--protocol", "all", "--output", str(growth)])
    if rc == cli.EXIT_OK:
        log.info(comm, "\ndemo done:\n"
                       f"  signaling figure (Fig. 3A-E analog): {(sig / 'protocols.png').resolve()}\n"
                       f"  growth figure (Fig. 4C-E analog):    {(growth / 'idealized_growth.png').resolve()}\n"
                       f"  time series (HDF5):                  {growth.resolve()}/idealized_<protocol>.h5\n"
                       f"  ParaView (open with the XDMF3 reader): {growth.resolve()}/idealized_<protocol>_fields.xdmf")
    return rc


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
