"""The parameters of the signaling model (MODEL.md §1, Table 2 of the paper).

Every field is a float or a 1-D array of per-member values (the batch axis: mesh
cells of one rank, samples of a Sobol analysis); all are validated when the dataclass
is built, so bad parameters never reach an integrator.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.core import params as common
from hyper.core.params import InputError

Array = float | np.ndarray


@dataclass(frozen=True)
class SignalingParams:
    """Table 2 of the paper (MODEL.md §1). Every field is a float or an array of per-member values."""

    a10: Array = 0.09  # 1/h, IGF1 baseline growth rate
    a20: Array = 0.4875  # 1/h, AKT baseline growth rate
    a3: Array = 0.01068  # 1/h, FOXO growth rate
    a4: Array = 0.004635  # 1/h, mTOR growth rate
    b1: Array = 2.0  # 1/h, IGF1 self-inhibition
    b2: Array = 0.5  # 1/h, AKT self-inhibition
    b3: Array = 0.02  # 1/h, FOXO self-inhibition
    b4: Array = 0.01  # 1/h, mTOR self-inhibition
    c21: Array = 0.2846  # 1/h, IGF1 -> AKT
    c32: Array = 0.002  # 1/h, AKT -| FOXO
    c42: Array = 0.001139  # 1/h, AKT -> mTOR
    c43: Array = 0.0025  # 1/h, FOXO -| mTOR
    kM: Array = 0.01  # 1/h, protein synthesis rate
    kF: Array = 0.019  # 1/h, protein degradation rate
    Nmin: Array = 0.5  # -, lower end of the admissible myofibril range
    Nmax: Array = 1.3  # -, upper end of the admissible myofibril range
    thetaF: Array = 0.434  # -, FOXO threshold
    thetaM: Array = 0.469  # -, mTOR threshold
    tau_h: Array = 6.0  # h, AKT transient time scale
    t1: Array = 17.0  # h, AKT transient delay
    tau_d: Array = 12.0  # h, IGF1 stimulus delay
    beta: Array = 2.0 / 50.0  # 1/(h kgf), stimulus scale
    Fmax: Array = 150.0  # kgf, maximal force capacity

    # rates that vanish make the model degenerate (no equilibrium, a frozen species)
    POSITIVE = ("a10", "a20", "a3", "a4", "b1", "b2", "b3", "b4", "tau_h", "Fmax", "Nmax")

    def __post_init__(self):
        sizes = set()
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if np.ndim(value) == 0:
                value = common.as_float(value.item() if isinstance(value, (np.ndarray, np.generic)) else value, f.name)
            else:
                value = np.array(value, dtype=float)
                if value.ndim != 1 or value.size == 0:
                    raise InputError(f"{f.name}: per-member values must be a non-empty 1-D array, "
                                     f"got shape {value.shape}")
                if not np.all(np.isfinite(value)):
                    raise InputError(f"{f.name}: every per-member value must be finite")
                value.setflags(write=False)
                sizes.add(value.size)
            object.__setattr__(self, f.name, value)
        if len(sizes) > 1:
            raise InputError(f"per-member parameter arrays differ in length: {sorted(sizes)}")
        object.__setattr__(self, "_size", sizes.pop() if sizes else None)
        common.check_positive(self, *self.POSITIVE)
        for name in ("c21", "c32", "c42", "c43", "kM", "kF", "Nmin", "thetaF", "thetaM", "t1", "tau_d", "beta"):
            if np.any(np.asarray(getattr(self, name)) < 0):
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if np.any(np.asarray(self.Nmin) >= np.asarray(self.Nmax)):
            raise InputError(f"Nmin must be < Nmax, got Nmin={self.Nmin!r}, Nmax={self.Nmax!r}")

    @property
    def size(self) -> int | None:
        """The number of members if some field is an array, else None."""
        return self._size

    def take(self, index) -> SignalingParams:
        """The members at ``index`` (an index array); scalar fields stay scalar."""
        return dataclasses.replace(
            self,
            **{
                f.name: getattr(self, f.name)[index]
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)
            },
        )

    def member(self, i: int) -> SignalingParams:
        """Member ``i`` with plain float fields."""
        return dataclasses.replace(
            self,
            **{
                f.name: float(getattr(self, f.name)[i])
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)
            },
        )


def load_params(path: str | Path | None = None, **overrides) -> SignalingParams:
    """Table values, overridden by a TOML file whose keys are field names, then by keywords."""
    return common.load_params(SignalingParams, path, **overrides)

