"""The ``cpu`` rasterizer backend of several source trees side by side: ``python -m rtsplat.bench.raster_cpu``.

``--checkout DIR`` (repeatable; default: the checkout this script belongs to) names source trees
whose ``rtsplat`` package is timed: one worker process per checkout runs this file with
``PYTHONPATH=DIR`` (a base copy: ``git archive <commit> | tar -x -C /tmp/base``). Every worker
renders the same sphere scene (:func:`rtsplat.bench.raster.sphere_scene`, float32) with the ``cpu``
backend; per cell (image size, surfel count, thread count) it times ``--repeats`` forward+backward
steps (forward with autograd, backward of a random mix of every output) and reports the medians of
the whole step and of the compositing forward and backward (the backend's autograd function,
measured by wrapping it from outside; everything between, projection, binning and the autograd of
the projection, is the rest of the step). Rounds are interleaved over the workers, the order
alternating, so every checkout sees the same machine load; the printed ratios are first / last
checkout, median over the rounds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def timed_compositing(spent: dict[str, float]):
    """While inside, every call of the ``cpu`` backend's compositing forward and backward (its autograd
    function, wrapped from outside) adds its wall seconds to ``spent["forward"]`` / ``spent["backward"]``;
    the function is restored on leaving. Defined in this file, not in the package, because a worker runs this
    file against the ``rtsplat`` of any checkout."""
    import rtsplat.raster.cpu as cpu

    composite = cpu._Composite
    forward, backward = composite.forward, composite.backward

    def timed(name, fn):
        def call(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - start

        return staticmethod(call)

    composite.forward, composite.backward = timed("forward", forward), timed("backward", backward)
    try:
        yield spent
    finally:
        composite.forward, composite.backward = staticmethod(forward), staticmethod(backward)


# -- worker: one checkout ------------------------------------------------------------------------
def _worker() -> int:
    totals = {"forward": 0.0, "backward": 0.0}
    with timed_compositing(totals):
        return _serve(totals)


def _serve(totals: dict[str, float]) -> int:
    """The worker's loop: the warm-up, then one reply per request, the compositing timed into ``totals``."""
    import torch

    import rtsplat
    from rtsplat.bench.raster import _loss, sphere_scene, with_grad
    from rtsplat.camera import camera_from_fov
    from rtsplat.raster import rasterize

    def step(scene, camera):
        leaf = with_grad(scene)
        totals["forward"] = totals["backward"] = 0.0
        t0 = time.perf_counter()
        _loss(rasterize(leaf, camera, backend="cpu")).backward()
        return time.perf_counter() - t0, totals["forward"], totals["backward"]

    t0 = time.perf_counter()
    warm_camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=32, height=24, fov_x_deg=50.0)
    step(sphere_scene(200), warm_camera)
    _send({"package": str(Path(rtsplat.__file__).parent), "warmup_s": time.perf_counter() - t0})
    scenes: dict[int, object] = {}
    for line in sys.stdin:
        request = json.loads(line)
        if request["cmd"] == "quit":
            break
        width, height, n, threads = request["width"], request["height"], request["surfels"], request["threads"]
        torch.set_num_threads(threads)
        if n not in scenes:
            scenes[n] = sphere_scene(n)
        camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=width, height=height, fov_x_deg=50.0)
        runs = [step(scenes[n], camera) for _ in range(request["repeats"])]
        _send({key: statistics.median(r[i] for r in runs) for i, key in enumerate(("step", "fwd", "bwd"))})
    return 0


def _send(data: dict) -> None:
    sys.stdout.write("@@" + json.dumps(data) + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.bench.raster_cpu", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkout", type=Path, action="append",
                        help="source tree to time (repeatable; default: this one); ratios are first / last")
    parser.add_argument("--cells", default="640x480:100000,100x75:8000",
                        help="WxH:surfels list (default: 640x480:100000,100x75:8000)")
    parser.add_argument("--threads", default="1,2", help="thread counts (default: 1,2)")
    parser.add_argument("--repeats", type=int, default=3, help="steps per cell and round (median; default 3)")
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds (default 2)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return _worker()
    from rtsplat.bench.workers import CheckoutWorker  # the parent only: a worker's checkout may lack it
    cells = []
    for item in args.cells.split(","):
        size, n = item.split(":")
        width, height = (int(v) for v in size.lower().split("x"))
        for threads in (int(t) for t in args.threads.split(",")):
            cells.append({"width": width, "height": height, "surfels": int(n), "threads": threads})
    checkouts = [c.resolve() for c in (args.checkout or [Path(__file__).resolve().parents[2]])]
    workers = []
    try:
        for checkout in checkouts:  # warm-ups (kernel compilation or cache load) one at a time
            w = CheckoutWorker(__file__, checkout, ["--worker"], f"@ {checkout}")
            info = w.receive()
            workers.append(w)
            print(f"[{len(workers) - 1}] {checkout}: package {info['package']}, warm-up {info['warmup_s']:.1f} s",
                  flush=True)
        results = {ci: {i: [] for i in range(len(cells))} for ci in range(len(checkouts))}
        for r in range(args.rounds):
            for i, cell in enumerate(cells):
                order = list(range(len(checkouts)))
                if (r + i) % 2:
                    order.reverse()
                for ci in order:
                    results[ci][i].append(workers[ci].ask({"cmd": "run", "repeats": args.repeats, **cell}))
    finally:
        for w in workers:
            w.close()
    print(f"\nms, median of {args.repeats} steps per round, median over {args.rounds} interleaved rounds; "
          "fwd / bwd = the compositing autograd function, step = forward+backward of the whole rasterizer")
    head = f"{'image':>8} {'surfels':>7} {'thr':>3} | " + " | ".join(
        f"[{ci}] {'fwd':>7} {'bwd':>7} {'step':>7}" for ci in range(len(checkouts)))
    if len(checkouts) > 1:
        head += f" | {'ratio fwd':>9} {'bwd':>6} {'step':>6}"
    print(head)
    print("-" * len(head))
    last = len(checkouts) - 1
    for i, cell in enumerate(cells):
        cols = []
        for ci in range(len(checkouts)):
            med = {k: statistics.median(run[k] for run in results[ci][i]) * 1e3 for k in ("fwd", "bwd", "step")}
            cols.append(f"    {med['fwd']:>7.1f} {med['bwd']:>7.1f} {med['step']:>7.1f}")
        line = f"{cell['width']}x{cell['height']:<4} {cell['surfels']:>7} {cell['threads']:>3} | " + " | ".join(cols)
        if last:
            ratios = [statistics.median(a[k] / b[k] for a, b in zip(results[0][i], results[last][i], strict=True))
                      for k in ("fwd", "bwd", "step")]
            line += f" | {ratios[0]:>9.2f} {ratios[1]:>6.2f} {ratios[2]:>6.2f}"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
