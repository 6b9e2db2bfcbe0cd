"""Which numerical kernels this process computes with, as one line for a trial record.

NumPy and the OpenBLAS it bundles choose their SIMD kernels when they load, from the CPU
they find (NumPy's dispatch targets; OpenBLAS's ``DYNAMIC_ARCH`` core). Different kernels
round differently in the last bits. A seeded trial is bitwise repeatable on one kind of
host, but the same trial on a host of another CPU kind can end with RMSEs that differ in
their last digits (forcing OpenBLAS's Haswell kernels on a host that chose SkylakeX changed
every BSP trial's final RMSEs by up to 2.2e-6 relative, with the same targets). em-bench
stores this line with every trial, so that results of different kernels stay visible,
as results of different code do with the code version.
"""
from __future__ import annotations

import ctypes
import os
import platform
from importlib import metadata
from pathlib import Path

import numpy as np

#: Environment variables that override the kernels the libraries would choose.
KERNEL_OVERRIDES = ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES", "NPY_ENABLE_CPU_FEATURES")
#: Names under which OpenBLAS builds export ``get_corename`` (NumPy's wheels prefix theirs).
_CORENAME_SYMBOLS = ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename",
                     "openblas_get_corename64_", "openblas_get_corename")


def openblas_core() -> str | None:
    """The OpenBLAS core (kernel set) NumPy's bundled OpenBLAS chose, e.g. ``SkylakeX``;
    None when this NumPy bundles no OpenBLAS that reports it (e.g. a system BLAS)."""
    bundled = Path(np.__file__).resolve().parent.with_name("numpy.libs")
    for library in sorted(bundled.glob("*openblas*.so*")):
        try:
            loaded = ctypes.CDLL(str(library))  # NumPy loaded it: the same instance
        except OSError:
            continue
        for symbol in _CORENAME_SYMBOLS:
            corename = getattr(loaded, symbol, None)
            if corename is not None:
                corename.restype = ctypes.c_char_p
                name = corename()
                return name.decode(errors="replace") if name else None
    return None


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "?"


def describe() -> str:
    """One line naming the kernels this process computes with, e.g. ``x86_64; NumPy 2.4.6
    (SIMD X86_V3 X86_V4 AVX512_ICL AVX512_SPR); OpenBLAS core SkylakeX; GTSAM 4.2``, with
    any override of ``KERNEL_OVERRIDES`` set in the environment appended."""
    simd = np.show_config(mode="dicts").get("SIMD Extensions", {}).get("found") or []
    parts = [platform.machine() or "?",
             f"NumPy {np.__version__} (SIMD {' '.join(simd) or 'baseline only'})",
             f"OpenBLAS core {openblas_core() or 'unknown'}",
             f"GTSAM {_version('gtsam')}"]
    overrides = [f"{name}={os.environ[name]}" for name in KERNEL_OVERRIDES
                 if os.environ.get(name)]
    return "; ".join(parts + overrides)
