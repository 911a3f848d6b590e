"""Ahead-of-time compilation of the ``triton`` backend's kernels for a CUDA GPU, on a machine without one.

``triton.compile`` runs the whole GPU tool chain (Triton IR -> LLVM -> PTX -> ptxas cubin) for an
sm_90 target from the kernels' source, with the constexprs and options that the backend launches
them with: a kernel that uses something the GPU compiler lacks fails here, although the interpreter
tests (``test_raster_triton.py``) pass. Runs in a subprocess: the interpreter tests set
``TRITON_INTERPRET=1`` in this process, and an interpreted kernel cannot be compiled.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="triton is not installed")

REPO = Path(__file__).resolve().parents[1]

# argument types as rtsplat.raster.gpu passes them: int32 lists and stop positions, int8 ``used`` flags,
# float tensors in the compute dtype, int32 sizes
COMPILE_ALL = """
    import json, sys
    import torch, triton
    from triton.backends.compiler import GPUTarget
    from rtsplat.raster import triton_kernels
    from rtsplat.raster.gpu import compile_options, kernel_constexprs

    INT_POINTERS = {"ids_ptr": "*i32", "tile_start_ptr": "*i32", "tile_count_ptr": "*i32", "stops_ptr": "*i32",
                    "used_ptr": "*i8"}
    results = []
    for dtype, float_type in ((torch.float32, "fp32"), (torch.float64, "fp64")):
        constexprs = kernel_constexprs(16, 12 + 3, dtype)  # the RT-Splatting G-buffer: 12 features + normal
        for kernel in (triton_kernels.forward_kernel, triton_kernels.backward_kernel):
            signature = {}
            for name in kernel.arg_names:
                if name in constexprs:
                    signature[name] = "constexpr"
                elif name in INT_POINTERS:
                    signature[name] = INT_POINTERS[name]
                elif name.endswith("_ptr"):
                    signature[name] = "*" + float_type
                else:
                    signature[name] = "i32"
            source = triton.compiler.ASTSource(fn=kernel, signature=signature, constexprs=constexprs)
            compiled = triton.compile(source, target=GPUTarget("cuda", 90, 32), options=compile_options(16))
            ptx, cubin = compiled.asm["ptx"], compiled.asm["cubin"]
            results.append(dict(
                kernel=kernel.__name__, dtype=float_type, ptx_entry=f".entry {kernel.__name__}" in ptx,
                ptx_target=".target sm_90" in ptx, cubin_elf=cubin[:4] == b"\\x7fELF", cubin_bytes=len(cubin),
                num_warps=compiled.metadata.num_warps,
            ))
    print(json.dumps(results))
"""


def test_every_kernel_compiles_to_ptx_and_cubin_for_sm90(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env.update(
        TRITON_CACHE_DIR=str(tmp_path / "cache"),  # an empty cache: really compile, and leave no files behind
        TRITON_DEFAULT_FP_FUSION="0",
        PYTHONPATH=os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]),
    )
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(COMPILE_ALL)], capture_output=True, text=True, env=env, timeout=300
    )
    assert result.returncode == 0, result.stderr[-4000:]
    compiled = json.loads(result.stdout.strip().splitlines()[-1])
    assert {(c["kernel"], c["dtype"]) for c in compiled} == {
        (k, d) for k in ("forward_kernel", "backward_kernel") for d in ("fp32", "fp64")
    }
    for c in compiled:
        assert c["ptx_entry"] and c["ptx_target"], c
        assert c["cubin_elf"] and c["cubin_bytes"] > 1000, c
        assert c["num_warps"] == 8, c
