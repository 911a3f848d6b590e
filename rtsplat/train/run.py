"""A training run: a :class:`~rtsplat.train.trainer.Trainer` driven over its schedule into its run folder.

The trainer owns the model, the optimizer, the step, the evaluation and the resumable state; the run owns
what a run folder holds and when it is written: starting or resuming, the provenance, the config and
effects files, the progress bar, the train log, the step timing, the periodic checkpoints, a stop on
request and the summary.

Run directory layout::

    <out>/config.json        resolved TrainConfig
    <out>/effects.json       which branches run and why (effects: auto)
    <out>/train_log.jsonl    one JSON line per logging step: losses, PSNR, surfels, seconds, cpu_seconds
    <out>/checkpoints/last.pt  resumable state (rtsplat.model.checkpoint, written atomically; never
                             a diverged one, and resuming needs the same config, see Trainer.load_checkpoint);
                             with a checkpoint_dir: <checkpoint_dir>/last.pt and a copy of train_log.jsonl
    <out>/model.pt           final state, same format;  <out>/point_cloud.ply  3DGS-viewer PLY
    <out>/summary.json       written last: a run without it is not finished; its starting_surfels says how
                             many surfels the SfM points started and why (rtsplat.train.initial), its
                             provenance the commit, uncommitted changes, machine, device and packages that
                             trained it (rtsplat.provenance; earlier_parts when a resume ran other code)

Time, in the log and the summary (:mod:`rtsplat.usage` says what each measure means): ``seconds`` /
``train_seconds`` are the wall seconds of the training steps (not the evaluations, test-view pose fits and
checkpoints between them), ``cpu_seconds`` / ``train_cpu_seconds`` this process's CPU seconds over the
same steps, which depend much less on what else the machine runs. The summary adds ``threads``,
``cpu_share`` (train_cpu_seconds / (train_seconds x threads)) and ``run_usage``: the usage of
:meth:`TrainingRun.train` as a whole (steps, evaluations, checkpoints; every resumed part included), with
``other_busy_cores``, the mean number of cores other processes kept busy meanwhile: how much ran beside it.
Before the first step the rasterizer's kernels are compiled or loaded (:mod:`rtsplat.train.warmup`), outside
the steps' seconds; the summary's ``kernel_warm_up_seconds`` says how long that took in the part that wrote it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rtsplat.io.atomic import write_errors, write_json_atomic, write_text_atomic
from rtsplat.io.train_log import LOG_NAME
from rtsplat.model.export import write_surfel_ply
from rtsplat.provenance import collect as collect_provenance
from rtsplat.provenance import commit_label, machine_label, run_record, same_source
from rtsplat.raster import default_backend
from rtsplat.train.clock import passed
from rtsplat.train.evaluation import best_test_psnr
from rtsplat.train.resume import restore_log
from rtsplat.train.warmup import warm_up_kernels
from rtsplat.usage import compute_threads

if TYPE_CHECKING:
    from rtsplat.train.trainer import StepResult, Trainer


class TrainingStopped(Exception):
    """:meth:`TrainingRun.train` stopped on request (:attr:`Trainer.stop_signal`) at an iteration boundary,
    after writing the checkpoint the next run resumes from."""

    def __init__(self, signal_number: int, iteration: int, checkpoint: Path):
        super().__init__(f"stopped by signal {signal_number} at iteration {iteration}; checkpoint {checkpoint}")
        self.signal_number = signal_number
        self.iteration = iteration
        self.checkpoint = checkpoint


class TrainingRun:
    """``trainer`` trained into its run folder (``trainer.out``)."""

    def __init__(self, trainer: Trainer):
        self.trainer = trainer
        self.log_path = trainer.out / LOG_NAME
        self.warm_up_seconds: float | None = None  # this part's kernel warm-up (rtsplat.train.warmup), once run

    def train(self, resume: bool = True, new_config: bool = False) -> dict:
        """Train to ``schedule.iterations``, resuming from ``checkpoints/last.pt`` when ``resume``
        (``new_config``: even if the config differs, see :meth:`Trainer.load_checkpoint`), and return the
        summary. A loss, gradient or parameter that goes non-finite stops the run with
        :class:`~rtsplat.train.divergence.TrainingDiverged` before anything of that state is written."""
        t = self.trainer
        cfg = t.cfg
        t.run_clock.restart()
        t.out.mkdir(parents=True, exist_ok=True)
        self._resume_or_start(resume, new_config)
        self._record_provenance()
        write_json_atomic(t.out / "config.json", cfg.to_dict())
        write_effects(t)
        self._log_settings()
        warm = warm_up_kernels(t)
        self.warm_up_seconds = round(warm.seconds, 3)
        t.log(f"kernels ready in {warm.seconds:.1f} s (compiled, or loaded from numba's cache; not in the "
              "training's seconds)")
        # reading the divergence record waits for the device: on a CPU that costs nothing, elsewhere it
        # is read where the loop reads the device anyway (logging steps) and before every write
        watch_every_step = t.device.type == "cpu"
        bar = _progress(cfg.schedule.iterations, t.clock.position, t.progress)
        with write_errors(self.log_path), open(self.log_path, "a") as log_file:
            if cfg.schedule.eval_every > 0 and t.iteration == 0:  # the initialisation, for comparison
                log_file.write(json.dumps({"iteration": 0, "seconds": 0.0, "cpu_seconds": 0.0,
                                           "surfels": len(t.model.surfels), **t.evaluate()}) + "\n")
            last = t.clock.done(t.iteration, t.elapsed)  # a resumed run may be done already
            while not last:
                step, numbers, last, evaluate_now = self._timed_step(watch_every_step)
                bar.update(step.positions[1] - step.positions[0])
                if numbers is not None:
                    bar.set_postfix(loss=f"{numbers['loss']:.4f}", psnr=f"{numbers['psnr']:.2f}",
                                    surfels=len(t.model.surfels))
                    log_file.write(json.dumps(self._log_record(step, numbers, last, evaluate_now)) + "\n")
                    log_file.flush()
                stop = t.stop_signal
                if stop is not None or passed(*step.positions, cfg.schedule.checkpoint_every) is not None:
                    log_file.flush()
                    self._write_checkpoint_and_log()
                if stop is not None and not last:
                    bar.close()
                    raise TrainingStopped(stop, t.iteration, t.checkpoint_path)
        bar.close()
        return self.finish()

    def _resume_or_start(self, resume: bool, new_config: bool) -> None:
        """Resume from the checkpoint when asked and there is one (the train log cut back to it), else start
        over (without a train log)."""
        t = self.trainer
        if resume and t.checkpoint_path.exists():
            t.load_checkpoint(t.checkpoint_path, new_config)
            t.log(f"resumed from {t.checkpoint_path} at iteration {t.iteration}")
            restore_log(self.log_path, t.kept_log_path, t.iteration, t.log)
        else:
            self.log_path.unlink(missing_ok=True)

    def _record_provenance(self) -> None:
        """Add what trains this part of the run (:func:`rtsplat.provenance.collect`) when it differs from what
        trained the part it resumes."""
        t = self.trainer
        here = collect_provenance(str(t.device))
        if not t.provenance or not same_source(t.provenance[-1], here):
            t.provenance.append(here)
        t.log(f"trained by: {commit_label(here)} on {machine_label(here)}")

    def _log_settings(self) -> None:
        """Say which branches run and why, the starting surfels, the device and the time budget."""
        t = self.trainer
        cfg, reasons = t.cfg, t.effect_reasons
        t.log(f"effects: transmission={t.effects.transmission} ({reasons['transmission']}), "
              f"specular={t.effects.specular} ({reasons['specular']})")
        t.log(f"near reflection: {t.effects.near_reflection} ({reasons['near_reflection']})")
        t.log(f"per-view appearance: {t.appearance is not None} ({reasons['appearance']})")
        t.log(f"perceptual loss: {t.perceptual_note}")
        t.log(f"starting surfels: {t.starting.surfels} ({t.starting.reason})")
        first = t.density_start.first_step
        t.log(f"density control from iteration {t.density_start.densify_from}, the first step at "
              f"{'none' if first is None else first} ({t.density_start.reason})")
        backend = default_backend(t.device) if cfg.backend == "auto" else cfg.backend
        t.log(f"device: {t.device} (train.device: {cfg.device}), rasterizer backend: {backend}, specular "
              f"network's products: {t.model.specular_products() or 'no network'}")
        if cfg.schedule.seconds is not None:
            t.log(f"time budget: {cfg.schedule.seconds:g} s of training steps, the plan of "
                  f"{cfg.schedule.iterations} iterations placed by the share spent")
        if t.effects.specular and t.specular_gradient_share < 1:
            t.log(f"specular network's gradient: through a random {t.specular_gradient_share:g} of the shaded pixels "
                  "per training render (schedule.specular_gradient_share)")

    def _timed_step(self, watch_every_step: bool) -> tuple[StepResult, dict[str, float] | None, bool, bool]:
        """One training step, its wall and CPU seconds added to the run's: the step, its numbers (read from the
        device on logging steps only, else None), whether it is the last and whether an evaluation follows.
        The divergence watch is read on logging steps, and on every step with ``watch_every_step``."""
        t = self.trainer
        schedule = t.cfg.schedule
        start, cpu_start = time.perf_counter(), time.process_time()
        try:
            step = t.step()
        except Exception:  # a diverged state can break the step itself: name the divergence
            t.stop_if_diverged()
            raise
        last = t.clock.done(step.iteration, t.elapsed + time.perf_counter() - start)
        evaluate_now = schedule.eval_every > 0 and (last or passed(*step.positions, schedule.eval_every) is not None)
        logging = step.iteration % schedule.log_every == 0 or last or evaluate_now or bool(step.density)
        # the loop reads the device only on logging steps; that read waits for the queued work,
        # so the seconds logged there include it
        numbers = step.numbers() if logging else None
        if logging or watch_every_step:
            t.stop_if_diverged()
        t.elapsed += time.perf_counter() - start
        if t.cpu_elapsed is not None:
            t.cpu_elapsed += time.process_time() - cpu_start
        return step, numbers, last, evaluate_now

    def _log_record(self, step: StepResult, numbers: dict[str, float], last: bool, evaluate_now: bool) -> dict:
        """The train log's line of a logging step; with ``evaluate_now``, the test views are fitted and
        evaluated first (with the final fit's steps on the ``last`` step)."""
        t = self.trainer
        cfg = t.cfg
        record = {"iteration": step.iteration, "seconds": round(t.elapsed, 4),
                  "cpu_seconds": _rounded(t.cpu_elapsed, 4), **numbers,
                  "surfels": len(t.model.surfels), "stage": step.stage}
        if cfg.schedule.seconds is not None:  # the plan's iteration this step stood at
            record["position"] = step.positions[1]
        if cfg.schedule.coarse_downsample > 1:  # the progressive resolution's factor of this step
            record["downsample"] = cfg.schedule.downsample_at(step.positions[1])
        if step.density:
            record["density"] = step.density
        if evaluate_now:
            t.fit_test_cameras(cfg.cameras.final_fit_steps if last else cfg.cameras.test_fit_steps)
            record.update(t.evaluate())
        return record

    def _write_checkpoint_and_log(self) -> None:
        """The checkpoint, after the kept copy of the train log (:attr:`Trainer.kept_log_path`): never older
        than it."""
        t = self.trainer
        if t.kept_log_path is not None:
            write_text_atomic(t.kept_log_path, self.log_path.read_text())
        t.save_checkpoint()

    def finish(self) -> dict:
        """The final evaluation, ``model.pt``, ``point_cloud.ply`` and, last, ``summary.json`` (returned)."""
        t = self.trainer
        if not t.cfg.schedule.eval_every:  # otherwise the last step's evaluation fitted them
            t.fit_test_cameras(t.cfg.cameras.final_fit_steps)
        metrics = t.evaluate()
        t.save_checkpoint(t.out / "model.pt")
        write_surfel_ply(t.out / "point_cloud.ply", t.model.surfels, t.model.uses_opacity)
        threads = compute_threads()
        share = t.cpu_elapsed / (t.elapsed * threads) if t.cpu_elapsed is not None and t.elapsed > 0 else None
        usage = t.run_usage()
        summary = {"iterations": t.iteration, "time_budget_seconds": t.cfg.schedule.seconds,
                   "train_seconds": round(t.elapsed, 3),
                   "train_cpu_seconds": _rounded(t.cpu_elapsed, 3), "threads": threads,
                   "cpu_share": _rounded(share, 3), "device": str(t.device),
                   "run_usage": None if usage is None else usage.to_dict(),
                   "seconds_per_iteration": round(t.elapsed / max(t.iteration, 1), 5),
                   "kernel_warm_up_seconds": self.warm_up_seconds,
                   "surfels": len(t.model.surfels), "starting_surfels": t.starting.to_dict(),
                   "density_start": t.density_start.to_dict(),
                   "effects": t.effects.to_dict(), "specular_products": t.model.specular_products(),
                   "specular_gradient_share": t.specular_gradient_share if t.effects.specular else None,
                   "near_reflection": t.near_fit, "appearance": t.appearance_summary(),
                   "mirror_planes_moved": None if t.plane_refinement is None else t.plane_refinement.moved(),
                   "provenance": run_record(t.provenance),
                   **metrics,
                   **t.correction_sizes(),
                   **best_test_psnr(self.log_path, t.iteration, metrics)}
        write_json_atomic(t.out / "summary.json", summary)
        t.log(f"done: {json.dumps(summary)}")
        return summary


def write_effects(trainer: Trainer) -> None:
    """``effects.json``: which branches run and why, the perceptual loss, the mirror-plane fit and the planes,
    the per-view appearance; written as the run starts and again when the trainer fits the mirror planes."""
    t = trainer
    write_json_atomic(t.out / "effects.json", {**t.effects.to_dict(), "reasons": t.effect_reasons,
                                               "perceptual": t.perceptual_note, "near_fit": t.near_fit,
                                               "appearance": t.appearance is not None,
                                               "appearance_spread": t.exposure.spread,
                                               "mirror_planes": t.model.mirror_planes.tolist()})


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def _progress(total: int, initial: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, desc="train", unit="it", dynamic_ncols=True)
