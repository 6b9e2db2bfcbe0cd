"""An OpenBLAS core type other than the host's, for tests that need a process computing with
other kernels (issue 40, point 8: the suite passes whatever OPENBLAS_CORETYPE the host
presets; forcing Haswell on a host whose environment already had OPENBLAS_CORETYPE=Haswell
made "another kernel" the same one)."""
from __future__ import annotations

import platform

#: OPENBLAS_CORETYPE values the DYNAMIC_ARCH OpenBLAS of NumPy's wheel accepts on any x86-64
#: CPU NumPy 2 runs on (SSE4.2 at least), with the core name it then reports (measured with
#: the pinned wheel: Prescott runs the Katmai kernels). Newer ones (Sandybridge: AVX,
#: Haswell: AVX2) may need instructions the host lacks. Prescott comes second: the Katmai
#: kernels size their blocks from OPENBLAS_L2_SIZE (KiB), and a preset given in bytes
#: (262144, i.e. 256 MiB) made a 200 x 200 product run for minutes (Nehalem: 0.2 s).
X86_64_CORE_TYPES = {"Nehalem": "Nehalem", "Prescott": "Katmai"}


def other_core_type(*host: str | None) -> tuple[str, str] | None:
    """``(OPENBLAS_CORETYPE value, core name OpenBLAS reports for it)`` of the first core in
    ``X86_64_CORE_TYPES`` that is none of ``host`` (core types or core names: the host's
    preset OPENBLAS_CORETYPE, the core its OpenBLAS reports), case-insensitively; None on a
    host that is not x86-64."""
    if platform.machine() != "x86_64":
        return None
    avoid = {name.lower() for name in host if name}
    for core_type, core_name in X86_64_CORE_TYPES.items():
        if core_type.lower() not in avoid and core_name.lower() not in avoid:
            return core_type, core_name
    raise AssertionError(f"no OpenBLAS core type other than {sorted(avoid)}")
