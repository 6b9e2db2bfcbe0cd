"""The numerical kernels a process names for its trial records (tools/math_platform.py)."""
import os
import platform
import subprocess
import sys

import numpy as np
import pytest

from em_exploration_ros.tools import math_platform
from openblas_cores import other_core_type

DESCRIBE = "from em_exploration_ros.tools import math_platform; print(math_platform.describe())"


def describe_in_child(**environment: str) -> str:
    env = {name: value for name, value in os.environ.items()
           if name not in math_platform.KERNEL_OVERRIDES}
    result = subprocess.run([sys.executable, "-c", DESCRIBE], env={**env, **environment},
                            capture_output=True, text=True, timeout=60, check=True)
    return result.stdout.strip()


def test_the_description_names_numpy_simd_openblas_core_and_gtsam():
    text = math_platform.describe()
    simd = np.show_config(mode="dicts")["SIMD Extensions"]["found"]
    assert f"NumPy {np.__version__} (SIMD {' '.join(simd)})" in text
    core = math_platform.openblas_core()
    assert core  # the pinned NumPy wheel bundles OpenBLAS and reports its core
    assert f"OpenBLAS core {core}" in text and "GTSAM " in text


@pytest.mark.skipif(platform.machine() != "x86_64",
                    reason="the OpenBLAS core types forced here exist on x86_64 only")
def test_a_forced_openblas_core_is_named_with_its_override():
    natural = describe_in_child()  # no override, whatever this process's environment has
    assert "OPENBLAS_CORETYPE" not in natural
    natural_core = natural.split("OpenBLAS core ", 1)[1].split(";", 1)[0]
    core_type, core_name = other_core_type(natural_core)  # another core than the host's
    forced = describe_in_child(OPENBLAS_CORETYPE=core_type)
    assert f"OpenBLAS core {core_name};" in forced
    assert forced.endswith(f"; OPENBLAS_CORETYPE={core_type}")
