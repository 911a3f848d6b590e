"""Resuming a run from its checkpoint: whether this run may resume it, and the train log brought back to it.

:meth:`rtsplat.train.trainer.Trainer.load_checkpoint` refuses a checkpoint without a training state, one
written training on another prepared scene (the :meth:`~rtsplat.scene.PreparedScene.data_record`
fingerprint), one with other effects, and one whose config differs beyond
:data:`rtsplat.train_config.RESUME_MAY_CHANGE` unless the run was asked to resume with its new config
(``--resume-with-new-config``). The log lines written after the checkpoint are dropped: the resumed run
writes them again.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from rtsplat.io.atomic import write_text_atomic
from rtsplat.io.train_log import read_log
from rtsplat.model.checkpoint import Checkpoint, CheckpointError
from rtsplat.model.rtmodel import ActiveEffects
from rtsplat.train_config import TrainConfig, resume_differences


def check_resumable(checkpoint: Checkpoint, path: Path, data: dict | None, effects: ActiveEffects,
                    cfg: TrainConfig, new_config: bool) -> list[str]:
    """Raise :class:`CheckpointError` unless a run on ``data`` (the prepared scene's data record; None: a
    scene without a folder) with ``effects`` and ``cfg`` may resume ``checkpoint`` (read from ``path``);
    return the config keys that differ from the checkpoint's (allowed with ``new_config``)."""
    if not checkpoint.training:
        raise CheckpointError("has no training state to resume from; delete it to start over", path=path)
    recorded = checkpoint.training.get("data") or {}
    fingerprint = recorded.get("fingerprint")
    if data is not None and fingerprint and fingerprint != data["fingerprint"]:
        raise CheckpointError(
            f"was written training on another prepared scene: {recorded.get('path', '?')} (fingerprint "
            f"{recorded['fingerprint']}); this run's data {data['path']} has fingerprint "
            f"{data['fingerprint']}",
            path=path, fix="pass the --data it was trained on to resume it, or use a new --out directory or "
            "--no-resume to start over on this data",
        )
    if checkpoint.effects != effects:
        raise CheckpointError(
            f"written with effects {checkpoint.effects.to_dict()}, this run uses {effects.to_dict()}; "
            "use a new --out directory or delete the checkpoint", path=path,
        )
    changed = resume_differences(checkpoint.training.get("config", {}), cfg)
    if changed and not new_config:
        raise CheckpointError(
            "was written with a different config than this run's:\n    " + "\n    ".join(changed),
            path=path, fix="pass --resume-with-new-config to resume with this config (Trainer.train("
            "new_config=True)), restore the checkpoint's config (its run's config.json), or use a new --out "
            "directory or --no-resume to start over",
        )
    return changed


def restore_log(path: Path, kept: Path | None, iteration: int, log: Callable[[str], None]) -> None:
    """The train log at ``path`` as it was at the checkpoint of ``iteration``: copied from ``kept`` (the
    checkpoint folder's copy) when the run folder lost it, then cut back (:func:`truncate_log`)."""
    if kept is not None and kept.exists() and not path.exists():
        write_text_atomic(path, kept.read_text())
    truncate_log(path, iteration, log)


def truncate_log(path: Path, iteration: int, log: Callable[[str], None]) -> None:
    """Drop log lines written after the checkpoint (they will be written again), and a last line that
    a killed run or a full disk left half-written (:func:`rtsplat.io.train_log.read_log`)."""
    if not path.exists():
        return
    kept = [line for record, line in read_log(path, log) if record["iteration"] <= iteration]
    write_text_atomic(path, "".join(line + "\n" for line in kept))
