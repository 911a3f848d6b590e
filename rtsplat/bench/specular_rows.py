"""The specular network's products per precision and row count: ``python -m rtsplat.bench.specular_rows``.

Times the network (:class:`rtsplat.model.specular.SpecularNetwork`'s MLP, forward and backward, on one
thread) in float32 and in bfloat16 (autocast) with three kinds of row counts: ``fixed`` (the same count
every step), ``changing`` (a new count every step, as the shaded pixels of a training are) and
``bucketed`` (the changing counts zero-padded to :func:`rtsplat.model.specular.bucketed_rows`, what the
network does in bfloat16 on a CPU). oneDNN compiles a bfloat16 kernel per new shape, so ``changing``
shows what that costs and ``bucketed`` what padding saves. The kinds run interleaved over ``--rounds``;
the median ms per step is printed. Ratios are comparable on a loaded machine, absolute times are not.

A second table times the bfloat16 network from its features (environment [M, 16], material [M, 4]) with the
changing counts, as a training runs it: the autocast reference
(:meth:`~rtsplat.model.specular.SpecularNetwork.mlp_outputs_reference`: outer product, concatenation, padding,
autocast MLP) against :class:`~rtsplat.model.specular.BFloat16Network` (the same products, numba kernels for the
input rows, the ReLUs and the features' gradient), interleaved, with the median of the per-round ratios.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from torch import nn

from rtsplat.model.specular import SpecularNetwork, bucketed_rows, cpu_has_bfloat16_matmul

KINDS = ("fixed", "changing", "bucketed")


def step_ms(mlp: nn.Module, rows: int, padded: int, bfloat16: bool) -> float:
    """One forward and backward of ``mlp`` on ``rows`` random rows (run on ``padded`` rows), in ms."""
    x = torch.randn(padded, mlp[0].in_features, requires_grad=True)
    start = time.perf_counter()
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bfloat16):
        out = mlp(x)[:rows].float()
    out.square().sum().backward()
    return 1000.0 * (time.perf_counter() - start)


def changing_count(rows: int, spread: int, draws: torch.Generator) -> int:
    """A row count of the ``changing`` kind: ``rows`` +- ``spread``, drawn from ``draws``."""
    return rows - spread + int(torch.randint(0, 2 * spread + 1, (1,), generator=draws))


def measure(rows: int, spread: int, steps: int, rounds: int, width: int, seed: int = 0) -> dict[tuple[str, str], float]:
    """Median ms per step of every (precision, kind), the kinds interleaved round by round."""
    torch.manual_seed(seed)
    mlp = SpecularNetwork(env_channels=16, material_channels=4, width=width, attenuation="network").mlp  # 80 in, 4 out
    draws = torch.Generator().manual_seed(seed)
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(rounds):
        for precision in ("float32", "bfloat16"):
            for kind in KINDS:
                per_step = []
                for _ in range(steps):
                    n = rows if kind == "fixed" else changing_count(rows, spread, draws)
                    padded = bucketed_rows(n) if kind == "bucketed" else n
                    per_step.append(step_ms(mlp, n, padded, precision == "bfloat16"))
                times.setdefault((precision, kind), []).append(statistics.median(per_step))
    return {key: statistics.median(values) for key, values in times.items()}


def feature_step_ms(net: SpecularNetwork, rows: int, reference: bool, generator: torch.Generator) -> float:
    """One forward and backward of ``net``'s MLP from ``rows`` random features, in ms."""
    env = torch.randn(rows, 16, generator=generator, requires_grad=True)
    material = torch.nn.functional.normalize(torch.randn(rows, 4, generator=generator), dim=-1).requires_grad_()
    start = time.perf_counter()
    out = (net.mlp_outputs_reference if reference else net.mlp_outputs)(env, material)
    out.square().sum().backward()
    return 1000.0 * (time.perf_counter() - start)


def measure_kernels(rows: int, spread: int, steps: int, rounds: int, width: int,
                    seed: int = 0) -> dict[str, list[float]]:
    """Median ms per step of each round for the autocast reference and the kernel pass, interleaved."""
    torch.manual_seed(seed)
    net = SpecularNetwork(env_channels=16, material_channels=4, width=width, precision="bfloat16",
                          attenuation="network")
    draws = torch.Generator().manual_seed(seed)
    times: dict[str, list[float]] = {"reference": [], "kernels": []}
    for name in times:  # untimed: the first kernel call loads (or compiles) the numba kernels
        feature_step_ms(net, rows, name == "reference", draws)
    for _ in range(rounds):
        for name in times:
            counts = [changing_count(rows, spread, draws) for _ in range(steps)]
            times[name].append(statistics.median(feature_step_ms(net, n, name == "reference", draws)
                                                 for n in counts))
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=7000, help="rows per step (shaded pixels; 100x75 is 7500)")
    parser.add_argument("--spread", type=int, default=500, help="changing counts: rows +- this, drawn per step")
    parser.add_argument("--steps", type=int, default=20, help="steps per kind and round")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    parser.add_argument("--width", type=int, default=256, help="hidden width (model.mlp_width)")
    args = parser.parse_args(argv)
    if args.rows <= args.spread or min(args.steps, args.rounds, args.width) < 1:
        parser.error("--rows must exceed --spread; --steps, --rounds and --width must be at least 1")
    print(f"native bfloat16 products on this CPU: {cpu_has_bfloat16_matmul()}; {args.rows} +- {args.spread} rows, "
          f"80-{args.width}-{args.width}-4, forward + backward, 1 thread, median ms per step")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = measure(args.rows, args.spread, args.steps, args.rounds, args.width)
        kernels = measure_kernels(args.rows, args.spread, args.steps, args.rounds, args.width)
    finally:  # the caller's thread count back (the tests call main in their own process)
        torch.set_num_threads(threads)
    print(f"{'precision':<10}" + "".join(f"{kind:>10}" for kind in KINDS))
    for precision in ("float32", "bfloat16"):
        print(f"{precision:<10}" + "".join(f"{result[(precision, kind)]:>10.2f}" for kind in KINDS))
    print("\nthe bfloat16 MLP from its features, changing counts (the reference pads them to buckets, as the kernels "
          "do)")
    for name, values in kernels.items():
        print(f"{name:<10}{statistics.median(values):>10.2f}")
    ratios = [a / b for a, b in zip(kernels["reference"], kernels["kernels"], strict=True)]
    print(f"median of the per-round ratios reference / kernels: {statistics.median(ratios):.2f}")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.specular_rows", main))
