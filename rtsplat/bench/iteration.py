"""Time of one training iteration, per phase: ``python -m rtsplat.bench.iteration --scene DIR``.

Trains rtsplat and 2dgs (transmission and specular off) on a prepared scene at the demo's settings
(the training options of demo/config.yaml, read from the checkout this script belongs to: 750
iterations, 64x128 environment map with 6 levels, the compressed schedule, its pruning and rates;
evaluations, checkpoints and logging off). A method's options and ``--options`` are merged over them
key by key. Each (checkout, method) pair runs in its own worker process. A process of the first
checkout first trains ``--warmup`` iterations (default 300: past ``specular_from``, so the full
model runs, at SH degree 2, after two densifications, so the surfel count is a trained one) and
writes the training state; every worker loads it (so all start from the same model and the same C
heap history) and times ``--iterations`` iterations per round. Rounds are
interleaved over the workers (the order alternates), so every worker sees the same load; the median
over the rounds is reported, and with two checkouts the median of the per-round ratios first / last.

``--checkout DIR`` (repeatable; default: the checkout this script belongs to) names source trees
whose ``rtsplat`` package is timed: the worker runs this file with ``PYTHONPATH=DIR``, so a second
checkout of an earlier commit (``git worktree add /tmp/base <commit>``, or ``git archive``) is
timed by the same script in the same run. Only names that exist in every checkout are wrapped.

Phases are explicit ``time.perf_counter`` sections, measured by wrapping functions from outside
(nothing in the package is instrumented): rasterizer projection, tile binning, compositing
forward and backward (the ``cpu`` backend's autograd function), environment lookup forward,
specular network forward, image loss forward (L1 + SSIM, SSIM alone listed too), the rest of the
render (SH colours, G-buffer arithmetic, gating), backward outside the rasterizer (autograd of the
network, environment map, losses, projection), density control, optimizer step, and the rest of
the iteration. Each time is exclusive of the sections nested inside it. ``--torch-profile N``
adds a torch.profiler table (self CPU time per operator, N iterations) per worker. Each worker also
gives its system CPU time (the kernel's, inside the total) and its minor page faults per iteration.
Workers set the C heap as ``rtsplat train`` does (:mod:`rtsplat.heap`; a checkout without that module
runs with glibc's defaults). Whether glibc's defaults fault pages depends on what the process freed
before, and a worker's history is not a training's: the setting's saving is measured on whole
``rtsplat train`` runs (docs/performance.md, "The C heap keeps what it frees").

``--finish`` trains every worker to the end of the schedule afterwards and prints its test PSNR.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

DEMO_CONFIG = Path(__file__).resolve().parents[2] / "demo" / "config.yaml"
# what the demo's training writes that a timing run leaves out
TIMING_SCHEDULE = {"eval_every": 0, "checkpoint_every": 0, "log_every": 10**9}
METHODS = {
    "rtsplat": {},
    # near reflections forced on (their planes fitted at specular_from, inside the warm-up) and off
    "rtsplat_near": {"effects": {"near_reflection": "on"}},
    "rtsplat_no_near": {"effects": {"near_reflection": "off"}},
    # near reflections that read the reflected surfels without training them (no backward of the mirrored pass)
    "rtsplat_near_reads": {"effects": {"near_reflection": "on"},
                           "model": {"near_reflection_trains_surfels": False}},
    # near reflections whose mirror planes are learnt from the images (rtsplat.train.planes)
    "rtsplat_near_planes": {"effects": {"near_reflection": "on"},
                            "lr": {"mirror_plane_rotation": 3e-4, "mirror_plane_shift": 1e-4}},
    # the attenuation beta as the specular network's fourth output (the paper's) instead of the material's head
    "rtsplat_paper_beta": {"model": {"attenuation_from": "network"}},
    # the specular network on every surface of the region of interest, opaque ones too (model.specular_surfaces
    # all; the default shades the see-through ones alone)
    "rtsplat_all_surfaces": {"model": {"specular_surfaces": "all"}},
    # the specular network's matrix products in float32 and in bfloat16 (model.specular_precision)
    "rtsplat_float32": {"model": {"specular_precision": "float32"}},
    "rtsplat_bfloat16": {"model": {"specular_precision": "bfloat16"}},
    # the specular network's hidden width halved (model.mlp_width)
    "rtsplat_mlp128": {"model": {"mlp_width": 128}},
    # the specular network's gradient through a quarter of the shaded pixels (schedule.specular_gradient_share)
    "rtsplat_gradient_share": {"schedule": {"specular_gradient_share": 0.25}},
    # the specular network on every pixel through the whole full stage (schedule.specular_coarse_share 0); the
    # default shades 2x2 blocks in the first half of the full stage, where the default warm-up (300) lands
    "rtsplat_full_res_specular": {"schedule": {"specular_coarse_share": 0.0}},
    # one effect alone: transmission without the specular branch (no environment map, no network), and the
    # specular branch without transmission (Ref-GS-like); with 2dgs they split rtsplat's extra cost by effect
    "rtsplat_no_specular": {"effects": {"transmission": "on", "specular": "off"}},
    "rtsplat_no_transmission": {"effects": {"transmission": "off", "specular": "on"}},
    "2dgs": {"effects": {"transmission": "off", "specular": "off"}},
}
PHASES = ("projection", "binning", "raster fwd", "raster bwd", "env lookup fwd", "specular net fwd",
          "ssim fwd", "image loss fwd (L1, rest)", "render (rest)", "backward (rest)", "density control",
          "optimizer", "iteration (rest)")


# -- worker: one checkout, one method ------------------------------------------------------------
class _Sections:
    """Exclusive perf_counter time per named section; sections may nest."""

    def __init__(self):
        self.totals: dict[str, float] = {}
        self._stack: list[list] = []  # [name, start, child time]

    def wrap(self, name: str, fn):
        sections = self

        def timed(*args, **kwargs):
            sections._stack.append([name, time.perf_counter(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                _, start, child = sections._stack.pop()
                spent = time.perf_counter() - start
                sections.totals[name] = sections.totals.get(name, 0.0) + spent - child
                if sections._stack:
                    sections._stack[-1][2] += spent

        timed.__wrapped__ = fn
        return timed

    def reset(self):
        self.totals = {}


def _instrument(sections: _Sections) -> None:
    import torch

    import rtsplat.raster.cpu as cpu
    import rtsplat.raster.reference as reference
    from rtsplat.model import envmap, specular
    from rtsplat.model.rtmodel import RTModel
    from rtsplat.train import losses
    from rtsplat.train.density import DensityControl
    from rtsplat.train.trainer import Trainer

    # projection and binning are looked up where the cpu backend's frame calls them (older checkouts
    # called them from rtsplat.raster.cpu itself)
    frame = cpu if hasattr(cpu, "project_surfels") else reference
    frame.project_surfels = sections.wrap("projection", frame.project_surfels)
    frame.bin_tiles = sections.wrap("binning", frame.bin_tiles)
    composite = cpu._Composite
    composite.forward = staticmethod(sections.wrap("raster fwd", composite.forward))
    composite.backward = staticmethod(sections.wrap("raster bwd", composite.backward))
    envmap.EnvironmentMap.forward = sections.wrap("env lookup fwd", envmap.EnvironmentMap.forward)
    specular.SpecularNetwork.forward = sections.wrap("specular net fwd", specular.SpecularNetwork.forward)
    losses.ssim_map = sections.wrap("ssim fwd", losses.ssim_map)
    losses.image_loss = sections.wrap("image loss fwd (L1, rest)", losses.image_loss)
    RTModel.render = sections.wrap("render (rest)", RTModel.render)
    torch.Tensor.backward = sections.wrap("backward (rest)", torch.Tensor.backward)
    DensityControl.observe = sections.wrap("density control", DensityControl.observe)
    DensityControl.step = sections.wrap("density control", DensityControl.step)
    Trainer._optimizer_step = sections.wrap("optimizer", Trainer._optimizer_step)
    Trainer.step = sections.wrap("iteration (rest)", Trainer.step)


def _worker(args) -> int:
    import torch

    import rtsplat
    from rtsplat.scene import PreparedScene
    try:
        from rtsplat.train_config import TrainConfig
    except ImportError:  # a --checkout from before the settings tree left rtsplat.train
        from rtsplat.train.config import TrainConfig
    from rtsplat.train.trainer import Trainer

    if args.threads:
        torch.set_num_threads(args.threads)
    try:  # the C heap as `rtsplat train` sets it (a --checkout from before rtsplat.heap runs glibc's defaults)
        from rtsplat.heap import keep_freed_memory
    except ImportError:
        pass
    else:
        keep_freed_memory()
    sections = _Sections()
    _instrument(sections)
    # the parent merged the demo's options, the method's and --options (method_options): a worker's checkout
    # may predate them
    cfg = TrainConfig.from_dict(json.loads(args.options))
    scene = PreparedScene.load(args.scene)
    with tempfile.TemporaryDirectory(prefix="rtsplat_bench_iteration_") as tmp:
        trainer = Trainer(scene, cfg, tmp, progress=False, log=lambda m: None)
        start = time.perf_counter()
        state = Path(args.state) if args.state else None
        if state is not None and state.exists():
            try:  # the state may come from a checkout whose config has other keys: load it as it is
                trainer.load_checkpoint(state, new_config=True)
            except TypeError:  # a checkout from before load_checkpoint(new_config=...)
                trainer.load_checkpoint(state)
        else:
            for _ in range(args.warmup):
                trainer.step()
            if state is not None:
                trainer.save_checkpoint(state)
        warm = time.perf_counter() - start
        _send({"ready": True, "package": str(Path(rtsplat.__file__).parent), "warmup_s": warm,
               "surfels": len(trainer.model.surfels), "threads": torch.get_num_threads(),
               "iteration": trainer.iteration})
        for line in sys.stdin:
            request = json.loads(line)
            if request["cmd"] == "run":
                sections.reset()
                times = []
                usage = resource.getrusage(resource.RUSAGE_SELF)
                for _ in range(request["iterations"]):
                    t0 = time.perf_counter()
                    trainer.step()
                    times.append(time.perf_counter() - t0)
                after = resource.getrusage(resource.RUSAGE_SELF)
                _send({"times": times, "phases": sections.totals, "surfels": len(trainer.model.surfels),
                       "iteration": trainer.iteration, "system_s": after.ru_stime - usage.ru_stime,
                       "page_faults": after.ru_minflt - usage.ru_minflt})
            elif request["cmd"] == "profile":
                from torch.profiler import ProfilerActivity, profile

                with profile(activities=[ProfilerActivity.CPU]) as prof:
                    for _ in range(request["iterations"]):
                        trainer.step()
                table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=request["rows"])
                _send({"table": table})
            elif request["cmd"] == "finish":
                while trainer.iteration < cfg.schedule.iterations:
                    trainer.step()
                _send({"metrics": trainer.evaluate(), "surfels": len(trainer.model.surfels),
                       "iteration": trainer.iteration})
            elif request["cmd"] == "quit":
                break
    return 0


def demo_options() -> dict:
    """The demo's training options (demo/config.yaml's ``rtsplat``, through :func:`rtsplat.config.trainer_options`)
    with its evaluations, checkpoints and logging off (:data:`TIMING_SCHEDULE`)."""
    from rtsplat.config import deep_merge, load_config, trainer_options
    from rtsplat.errors import PipelineError

    if not DEMO_CONFIG.is_file():
        raise PipelineError(f"{DEMO_CONFIG} is missing: the benchmark times the demo's settings",
                            fix="run it from a checkout of the repository (it reads demo/config.yaml)")
    demo = load_config(DEMO_CONFIG)
    return deep_merge(trainer_options(demo, demo.scenes[0], "rtsplat"), {"schedule": TIMING_SCHEDULE})


def demo_environment_map() -> dict:
    """The demo's environment map settings (``env_height``, ``env_width``, ``env_levels`` of
    :func:`demo_options`' model), for the benchmarks that train a toy model the demo's way."""
    model = demo_options()["model"]
    return {key: model[key] for key in ("env_height", "env_width", "env_levels")}


def method_options(method: str, options: dict | None = None) -> dict:
    """The training options of ``method``: the demo's (:func:`demo_options`), the method's merged over them, then
    ``options`` (``--options``), each merged key by key."""
    from rtsplat.config import deep_merge

    return deep_merge(deep_merge(demo_options(), METHODS[method]), options or {})


def _check_methods(methods: list[str], given: str) -> None:
    """Refuse a ``--methods`` list that is empty or names a method this script does not know, before any
    worker starts."""
    from rtsplat.errors import PipelineError

    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise PipelineError(f"--methods {given!r}: unknown {', '.join(unknown) or '(none given)'}",
                            fix=f"choose from {', '.join(METHODS)}")


def _send(data: dict) -> None:
    sys.stdout.write("@@" + json.dumps(data) + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.bench.iteration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=False, help="prepared scene directory")
    parser.add_argument("--checkout", type=Path, action="append",
                        help="source tree to time (repeatable; default: this one); ratios are first / last")
    parser.add_argument("--methods", default="rtsplat,2dgs",
                        help="comma-separated method names, from: " + ", ".join(METHODS))
    parser.add_argument("--warmup", type=int, default=300, help="untimed iterations first (default 300)")
    parser.add_argument("--iterations", type=int, default=20, help="timed iterations per round (default 20)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--options", default="{}", help="extra TrainConfig options as JSON, e.g. "
                        "'{\"model\": {\"mlp_width\": 64}}' (merged over the demo's sections)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch (and numba) threads per worker (default: torch's default, the core count)")
    parser.add_argument("--torch-profile", type=int, default=0, metavar="N",
                        help="also print a torch.profiler table of N iterations per worker")
    parser.add_argument("--finish", action="store_true", help="train to the end afterwards; print test PSNR")
    parser.add_argument("--state-dir", type=Path,
                        help="keep the warmed-up training states here (<method>.pt) and reuse them in later runs; "
                        "default: a temporary folder. A process of the first checkout warms up and writes them, and "
                        "every timed worker loads them, so every checkout times the same model from the same start")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--state", help=argparse.SUPPRESS)
    parser.add_argument("--method", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.scene is None:
        parser.error("--scene is required")
    if args.worker:
        return _worker(args)
    # the workers run in their checkouts: paths given relative to this folder are passed on absolute
    args.scene = args.scene.resolve()
    if args.state_dir is not None:
        args.state_dir = args.state_dir.resolve()
    from rtsplat.bench.workers import CheckoutWorker  # the parent only: a worker's checkout may lack it
    from rtsplat.errors import run_command
    from rtsplat.io.outputs import check_output_dir, mark_output

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    status = run_command(parser.prog, lambda: _check_methods(methods, args.methods))
    if status:
        return status

    if args.state_dir is not None:  # a folder of its own: created with the marker, reused when it has it
        status = run_command(parser.prog, lambda: check_output_dir(args.state_dir, "bench.iteration",
                                                                   flag="--state-dir"))
        if status:
            return status
    extra, trees = json.loads(args.options), {}
    status = run_command(parser.prog, lambda: trees.update({m: json.dumps(method_options(m, extra)) for m in methods}))
    if status:
        return status

    checkouts = [c.resolve() for c in (args.checkout or [Path(__file__).resolve().parents[2]])]
    workers: dict[tuple[int, str], CheckoutWorker] = {}
    tmp = None
    if args.state_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="rtsplat_bench_state_")
        args.state_dir = Path(tmp.name)
    args.state_dir.mkdir(parents=True, exist_ok=True)
    mark_output(args.state_dir, "bench.iteration")
    def start(checkout: Path, method: str) -> tuple[CheckoutWorker, dict]:
        w = CheckoutWorker(__file__, checkout, [
            "--worker", "--method", method, "--scene", str(args.scene), "--warmup", str(args.warmup),
            "--options", trees[method], "--state", str(args.state_dir / f"{method}.pt"),
            "--threads", str(args.threads)], f"{method} @ {checkout}")
        return w, w.receive()

    try:
        for method in methods:
            if not (args.state_dir / f"{method}.pt").exists():
                # the warm-up runs in a process of its own that writes the state and quits, so that every timed
                # worker loads it: a worker that trained the warm-up itself and one that loaded its result read up
                # to 25% apart in the same code (docs/performance.md, "The G-buffer channels by stage")
                warm, info = start(checkouts[0], method)
                warm.close()
                print(f"[{method}] warmed up to iteration {info['iteration']} in {info['warmup_s']:.1f} s by "
                      f"{checkouts[0]}", flush=True)
            for ci, checkout in enumerate(checkouts):  # one at a time: no competition
                w, info = start(checkout, method)
                workers[ci, method] = w
                print(f"[{method} @ {checkout}] package {info['package']}, at iteration {info['iteration']} "
                      f"after {info['warmup_s']:.1f} s (warm-up or state load), {info['surfels']} surfels, "
                      f"{info['threads']} torch threads", flush=True)
        runs: dict[tuple[int, str], list[dict]] = {key: [] for key in workers}
        for r in range(args.rounds):
            for method in methods:
                order = list(range(len(checkouts)))
                if r % 2:
                    order.reverse()
                for ci in order:
                    runs[ci, method].append(workers[ci, method].ask({"cmd": "run", "iterations": args.iterations}))
        _print_results(checkouts, methods, runs, args)
        if args.torch_profile:
            for key, w in workers.items():
                table = w.ask({"cmd": "profile", "iterations": args.torch_profile, "rows": 30})["table"]
                print(f"\ntorch.profiler, {args.torch_profile} iterations, {key[1]} @ {checkouts[key[0]]}:\n{table}")
        if args.finish:
            print("\ntest PSNR after the whole schedule:")
            for (ci, method), w in workers.items():
                res = w.ask({"cmd": "finish"})
                print(f"  {method:8s} @ {checkouts[ci]}: {json.dumps(res['metrics'])}, {res['surfels']} surfels",
                      flush=True)
    finally:
        for w in workers.values():
            w.close()
        if tmp is not None:
            tmp.cleanup()
    return 0


def _print_results(checkouts, methods, runs, args) -> None:
    print(f"\nms per training iteration: median over {args.rounds} interleaved rounds of {args.iterations} "
          "iterations (phases: exclusive perf_counter sections, median over rounds)")
    for method in methods:
        print(f"\n== {method}")
        names = [f"[{ci}] {c.name or c}" for ci, c in enumerate(checkouts)]
        print(f"{'phase':28s} " + " ".join(f"{n[:14]:>14s}" for n in names))
        per = {ci: runs[ci, method] for ci in range(len(checkouts))}
        for phase in PHASES:
            vals = [statistics.median(1e3 * r["phases"].get(phase, 0.0) / len(r["times"]) for r in per[ci])
                    for ci in per]
            print(f"{phase:28s} " + " ".join(f"{v:14.2f}" for v in vals))
        totals = [statistics.median(1e3 * sum(r["times"]) / len(r["times"]) for r in per[ci]) for ci in per]
        print(f"{'total ms/iteration':28s} " + " ".join(f"{v:14.2f}" for v in totals))
        system = [statistics.median(1e3 * r["system_s"] / len(r["times"]) for r in per[ci]) for ci in per]
        print(f"{'of which system CPU ms':28s} " + " ".join(f"{v:14.2f}" for v in system))
        faults = [statistics.median(r["page_faults"] / len(r["times"]) for r in per[ci]) for ci in per]
        print(f"{'page faults/iteration':28s} " + " ".join(f"{v:14.0f}" for v in faults))
        surf = [per[ci][-1]["surfels"] for ci in per]
        print(f"{'surfels (last round)':28s} " + " ".join(f"{v:14d}" for v in surf))
        if len(checkouts) > 1:
            ratios = [sum(a["times"]) / sum(b["times"]) for a, b in zip(per[0], per[len(checkouts) - 1], strict=True)]
            print(f"ratio [0] / [{len(checkouts) - 1}] per round: " + ", ".join(f"{x:.2f}" for x in ratios)
                  + f"; median {statistics.median(ratios):.2f}")


if __name__ == "__main__":
    raise SystemExit(main())
