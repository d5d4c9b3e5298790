"""The C backend of ``hyper.signaling``: its RK4 step compiled at run time through cffi.

Use it through ``signaling.integrate(..., backend="c" | "auto")``;
``signaling.c_backend_error`` builds it (ahead of timings) and says why it cannot be.
This module knows arrays, not protocols: the integrators cut [t0, t1] into pieces and
tabulate the stimuli, as for their numpy batch, and ``run`` takes each block of members
through those pieces on the compiled step.

The C code repeats the RK4 of ``hyper.model.signaling.integrators`` in its (h/2)-scaled form
expression for expression (``model.scalar_rhs`` and the single-member step): with
s = h/2 the rate constants and the stimuli come scaled by s, the stages are K_i = s k_i,
and y_new = y + ((K1 + K4) + 2 (K2 + K3)) / 3.
IEEE +, -, * are exactly rounded, so the same trees in the same order give the same bits;
``-ffp-contract=off`` keeps the compiler from fusing them into FMAs. A member that fails
(a non-finite or negative state) does not stop the others: its failure time is recorded
and it runs on as garbage, every lane independent of the others.

The compiler is the one FFCx uses (cffi through setuptools: ``$CC`` or Python's build
compiler). The library is built once per source, flags, CPU and Python, and cached in
``$HYPER_CACHE_DIR`` (default ``$XDG_CACHE_HOME/hyper``, else ``~/.cache/hyper``). Several
processes (MPI ranks) may build it at once: each compiles in its own temporary folder
next to the cache entry and renames the result into place, an atomic step on one file
system, so a process loads either nothing or a whole library.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

# Rows of the per-member coefficient matrix, in the order the C code reads them: first
# those that scale with the step (rates), then thresholds and bounds. The inhibitions c32
# and c43 enter negated, as in the model's right-hand sides; "kM" is the effective synthesis rate
# (signaling's kM override).
ROWS = ("b1", "b2", "b3", "b4", "a3", "a4", "c21", "c32", "c42", "c43", "kF", "kM",
        "thetaF", "thetaM", "Nmin", "Nmax")
SCALED = 12
NEGATED = ("c32", "c43")

# Members per call of the kernel: what a step reads (23 doubles per member: scaled rates,
# thresholds, state, stimuli) stays in a 48 KiB L1 cache. Measured best of 64 ... 8192 on
# the development machine (about 15 % over 2048).
BLOCK = 256

_CDEF = """
void rk4_piece(long n, long steps, double s, double third, double t0, double h, const double *P,
               const double *A1, const double *a20, const double *bumps, double *Y, double *fail_t);
"""

# Branches are written as selects so that GCC vectorizes the loop over members.
SOURCE = r"""
#include <math.h>

enum {B1, B2, B3, B4, A3, A4, C21, MC32, C42, MC43, KF, KM, THF, THM, NMIN, NMAX};
#define ROW(k) (P + (long)(k) * n)

static inline void rhs(long i, long n, const double *restrict P, double A1, double A2,
                       double x1, double x2, double x3, double x4, double N, double *k)
{
    k[0] = x1 * (A1 - ROW(B1)[i] * x1);
    k[1] = x2 * ((A2 - ROW(B2)[i] * x2) + ROW(C21)[i] * x1);
    k[2] = x3 * ((ROW(A3)[i] - ROW(B3)[i] * x3) + ROW(MC32)[i] * x2);
    k[3] = x4 * (((ROW(A4)[i] - ROW(B4)[i] * x4) + ROW(C42)[i] * x2) + ROW(MC43)[i] * x3);
    const double d3 = x3 - ROW(THF)[i], d4 = x4 - ROW(THM)[i];
    const double f = (d4 > 0.0 ? ROW(KM)[i] * d4 : 0.0) - (d3 > 0.0 ? ROW(KF)[i] * d3 : 0.0);
    const int inside = (ROW(NMIN)[i] <= N) & (N <= ROW(NMAX)[i]);
    k[4] = inside ? f : 0.0;
}

/* `steps` RK4 steps of size h = 2 s from t0 for n members; Y (5 x n) in place. P holds the
   rate constants times s; A1 is s a1; bumps holds a2 - a20 at the 2 steps + 1 stage times
   (zeros without a bump). fail_t[i] < 0 until member i first leaves [0, inf) or turns NaN,
   then the start time of that step. */
void rk4_piece(long n, long steps, double s, double third, double t0, double h,
               const double *restrict P, const double *restrict A1, const double *restrict a20,
               const double *restrict bumps, double *restrict Y, double *restrict fail_t)
{
    for (long j = 0; j < steps; ++j) {
        const double u0 = bumps[2 * j], u1 = bumps[2 * j + 1], u2 = bumps[2 * j + 2];
        const double t = t0 + j * h;
        for (long i = 0; i < n; ++i) {
            const double a1 = A1[i];
            const double x[5] = {Y[i], Y[n + i], Y[2 * n + i], Y[3 * n + i], Y[4 * n + i]};
            double K1[5], K2[5], K3[5], K4[5];
            rhs(i, n, P, a1, s * (a20[i] + u0), x[0], x[1], x[2], x[3], x[4], K1);
            rhs(i, n, P, a1, s * (a20[i] + u1), x[0] + K1[0], x[1] + K1[1], x[2] + K1[2], x[3] + K1[3],
                x[4] + K1[4], K2);
            rhs(i, n, P, a1, s * (a20[i] + u1), x[0] + K2[0], x[1] + K2[1], x[2] + K2[2], x[3] + K2[3],
                x[4] + K2[4], K3);
            rhs(i, n, P, a1, s * (a20[i] + u2), x[0] + (K3[0] + K3[0]), x[1] + (K3[1] + K3[1]),
                x[2] + (K3[2] + K3[2]), x[3] + (K3[3] + K3[3]), x[4] + (K3[4] + K3[4]), K4);
            int ok = 1;
            for (int c = 0; c < 5; ++c) {
                const double m = K2[c] + K3[c];
                double z = x[c] + ((K1[c] + K4[c]) + (m + m)) * third;
                if (c == 4) {  /* integrators.stop_at_bounds: N stops at the bound it crosses */
                    const double lo = x[4] < ROW(NMIN)[i] ? x[4] : ROW(NMIN)[i];
                    const double hi = x[4] > ROW(NMAX)[i] ? x[4] : ROW(NMAX)[i];
                    z = z < lo ? lo : (z > hi ? hi : z);
                }
                Y[c * n + i] = z;
                ok &= (z >= 0.0) & (z < INFINITY);
            }
            fail_t[i] = (!ok && fail_t[i] < 0.0) ? t : fail_t[i];
        }
    }
}
"""

# Without -ffp-contract=off GCC fuses a*b + c into FMAs under -march=native, and the bits
# differ from numpy's. -march=native buys AVX2 or AVX-512 (4 or 8 members per instruction
# instead of SSE2's 2); GCC uses 512-bit vectors only when asked: 1.4x on the development
# machine (Rocket Lake). Vector width never changes a lane's arithmetic. The portable flags
# are the fallback for compilers that reject the first set.
FLAGS = (["-O3", "-ffp-contract=off", "-march=native", "-mprefer-vector-width=512"], ["-O3", "-ffp-contract=off"])


class Unavailable(RuntimeError):
    """The kernel cannot be built or loaded here (no C compiler, no cffi, no writable cache)."""


def _cpu_tag() -> str:
    """What -march=native depends on: a cached kernel must not run on a different CPU."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        lines = [line for line in text.splitlines() if line.startswith(("model name", "flags"))][:2]
        return "\n".join(lines) or platform.processor()
    except OSError:
        return platform.machine() + platform.processor()


def cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(os.environ.get("HYPER_CACHE_DIR", Path(root) / "hyper"))


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _build(flags: list[str]):
    from cffi import FFI
    from cffi import __version__ as cffi_version

    key = "\0".join([SOURCE, _CDEF, *flags, _cpu_tag(), sys.version, cffi_version])
    name = f"_hyper_rk4_{hashlib.sha256(key.encode()).hexdigest()[:16]}"
    path = cache_dir() / f"{name}{importlib.machinery.EXTENSION_SUFFIXES[0]}"
    if path.exists():
        try:
            return _load(name, path)
        except ImportError:
            pass  # unloadable (another cffi build, a damaged file): build it anew over it
    path.parent.mkdir(parents=True, exist_ok=True)
    ffi = FFI()
    ffi.cdef(_CDEF)
    ffi.set_source(name, SOURCE, extra_compile_args=flags)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{name}.") as tmp:
        os.replace(ffi.compile(tmpdir=tmp), path)
    return _load(name, path)


# The outcome of the first build: the module, or why there is none. A failed build is
# remembered too, or every "auto" call would run the compiler again.
_KERNEL: dict = {}


def kernel():
    """The compiled kernel (a cffi module), built or loaded on first use; raises Unavailable."""
    if not _KERNEL:
        errors = []
        for flags in FLAGS:
            try:
                _KERNEL["module"], _KERNEL["flags"] = _build(flags), flags
                break
            except Exception as err:  # noqa: BLE001 - try the next flags, report all if none works
                errors.append(f"{' '.join(flags)}: {type(err).__name__}: {err}")
        else:
            _KERNEL["error"] = (
                "cannot build the compiled RK4 kernel (needs a C compiler and cffi, as DOLFINx's "
                f"FFCx does, and a writable cache folder {cache_dir()}). Tried: " + "; ".join(errors)
            )
    if "error" in _KERNEL:
        raise Unavailable(_KERNEL["error"])
    return _KERNEL["module"]


def kernel_flags() -> list[str]:
    """The compiler flags of the kernel in use (builds or loads it; raises Unavailable)."""
    kernel()
    return _KERNEL["flags"]


def coefficients(params, kM, n: int) -> np.ndarray:
    """The coefficient matrix (len(ROWS), n) of ``params`` (fields scalar or per member) and kM."""
    P = np.empty((len(ROWS), n))
    for k, name in enumerate(ROWS):
        value = np.asarray(kM if name == "kM" else getattr(params, name), dtype=float)
        P[k] = -value if name in NEGATED else value
    return P


def run(P: np.ndarray, a20, Y0: np.ndarray, plan, out: np.ndarray, fail_t: np.ndarray, third: float,
        stop: bool = False):
    """Take n members from Y0 (5, n) through the pieces of ``plan``, block by block.

    P: ``coefficients``; a20: scalar or (n,). Each piece of ``plan`` is (steps, h, a1, bumps,
    t0, out): a1 the unscaled IGF1 growth rate (scalar or (n,)), bumps a2 - a20 at the
    2 steps + 1 stage times (float64, contiguous), out the index into ``out``
    (len(times), 5, n) that receives the states at the piece's end, or -1. ``fail_t``
    (n,) receives the start of each member's first failing step, -1 where none failed.

    With ``stop``, returns at the end of the first piece in which a member of the block
    fails: (piece index, member, the member's state at the piece's start). Otherwise, and
    when nothing fails, returns None.
    """
    module = kernel()
    lib, ffi = module.lib, module.ffi
    n = Y0.shape[1]
    a20 = np.broadcast_to(np.asarray(a20, dtype=float), (n,))

    def ptr(a: np.ndarray):
        return ffi.cast("double *", a.ctypes.data)

    bumps = [ptr(piece[3]) for piece in plan]
    for start in range(0, n, BLOCK):
        sel = slice(start, min(start + BLOCK, n))
        m = sel.stop - sel.start
        Pb = np.ascontiguousarray(P[:, sel])
        Ps = Pb.copy()  # the rates times s = h/2 of the piece
        A1 = np.empty(m)
        a20b = np.ascontiguousarray(a20[sel])
        Y = np.ascontiguousarray(Y0[:, sel])
        before = np.empty_like(Y) if stop else None
        fb = np.full(m, -1.0)
        p_Ps, p_A1, p_a20, p_Y, p_fb = ptr(Ps), ptr(A1), ptr(a20b), ptr(Y), ptr(fb)
        for k, (steps, h, a1, _, t0, index) in enumerate(plan):
            s = 0.5 * h
            np.multiply(s, Pb[:SCALED], out=Ps[:SCALED])
            np.multiply(s, a1[sel] if np.ndim(a1) else a1, out=A1)
            if stop:
                np.copyto(before, Y)
            lib.rk4_piece(m, steps, s, third, t0, h, p_Ps, p_A1, p_a20, bumps[k], p_Y, p_fb)
            if stop and fb.max() >= 0.0:
                i = int(np.argmin(np.where(fb >= 0.0, fb, np.inf)))
                return k, start + i, before[:, i].copy()
            if index >= 0:
                out[index, :, sel] = Y
        fail_t[sel] = fb
    return None
