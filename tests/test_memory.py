"""The process memory policy: frame-sized buffers are reused, not faulted in again."""

import subprocess
import sys

import pytest

PROBE = r"""
import resource, sys
import numpy as np
from lightflow.app.memory import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory() and keep_freed_memory()  # idempotent
frame = np.empty((1200, 1600, 3), np.uint8)  # a 1600x1200 RGB frame, 5.8 MB
def one_frame():  # two frame-sized arrays alive at once, as a pipeline has
    a = frame.copy(); b = frame.copy(); del a, b
for _ in range(3):  # warm: the first frames may grow the heap
    one_frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    one_frame()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def faults_per_copy(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True,
                         check=True)  # fmt: skip
    return float(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_frame_sized_copies_reuse_their_memory_instead_of_faulting_it_in():
    # glibc returns the freed top of its heap to the kernel once more than twice the
    # largest block freed so far is free: two 5.8 MB arrays freed together are.  Measured
    # here: about 740 page faults per frame by default (in part 2 MiB pages), 0 with the
    # policy
    assert faults_per_copy("default") > 500
    assert faults_per_copy("keep") < 20
