"""Work done on one rank for all: its result, or its error, reaches every rank."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def on_rank0(comm, action: Callable[[], Any]) -> Any:
    """Run ``action`` on rank 0 and raise its error on every rank (collective)."""
    result = error = None
    if comm.rank == 0:
        try:
            result = action()
        except Exception as err:  # noqa: BLE001 - re-raised on every rank below
            error = err
    error = comm.bcast(error, root=0)
    if error is not None:
        raise error
    return comm.bcast(result, root=0)
