"""``make demo``: for now, the signaling model on the paper's three protocols (Fig. 3A–E analog).

Writes results/signaling/{mwf,every3days,weekly}.h5 and results/signaling/protocols.png.
"""

from __future__ import annotations

import sys
from pathlib import Path

from hyper import signaling


def main(argv=None) -> int:
    folder = Path("results/signaling")
    figure = folder / "protocols.png"
    rc = signaling.main(["--protocol", "all", "--output", str(folder), "--plot", str(figure)])
    if rc == 0:
        print(f"\ndemo: the figure is {figure.resolve()}")
        print(f"      the time series are {folder.resolve()}/<protocol>.h5 (datasets t, igf1, akt, foxo, mtor, N)")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
