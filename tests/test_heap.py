"""rtsplat.heap: the C heap keeps the pages a command frees, so buffers allocated again step after step do not
fault their pages in again."""

import subprocess
import sys
import textwrap

import pytest

from rtsplat.heap import _glibc

BLOCK, BLOCKS = 100 * 1024, 100
PAGES_PER_STEP = BLOCK * BLOCKS // 4096
# a step allocates a hundred 100 KB blocks from the C heap, writes them and frees them, as a training step
# does with its activations and gradients; with glibc's defaults free() hands the heap's freed top back to the
# kernel (past the 128 KB trim threshold), so the next step faults those pages in again
STEPS = textwrap.dedent(f"""
    import ctypes, resource, sys
    from rtsplat.heap import _glibc, keep_freed_memory
    applied = keep_freed_memory() if sys.argv[1] == "kept" else None
    libc = _glibc()
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
    libc.free.argtypes = (ctypes.c_void_p,)
    def step():
        blocks = [libc.malloc({BLOCK}) for _ in range({BLOCKS})]
        for block in blocks:
            ctypes.memset(block, 1, {BLOCK})
        for block in blocks:
            libc.free(block)
    faults = []
    for _ in range(12):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        step()
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    print(applied, sorted(faults[2:])[5])  # the median step after the first two (the heap grows first)
""")


def _faults_per_step(mode: str) -> tuple[str, int]:
    """Whether the setting took (``kept``; None otherwise) and the median step's page faults."""
    out = subprocess.run([sys.executable, "-c", STEPS, mode], capture_output=True, text=True, check=True)
    applied, faults = out.stdout.split()
    return applied, int(faults)


@pytest.mark.skipif(_glibc() is None, reason="the C library is not glibc")
def test_freed_blocks_are_reused_without_page_faults():
    applied, kept = _faults_per_step("kept")
    assert applied == "True"  # glibc took both thresholds
    assert kept < 0.01 * PAGES_PER_STEP, kept  # (almost) no page of the 2500 a step writes is faulted in again
    _, system = _faults_per_step("system")
    assert system > 0.1 * PAGES_PER_STEP, system  # glibc's defaults do fault them (544 pages a step here)
