"""Features and matches for the SfM stage: which pairs to match, and the databases that hold them.

The matcher is picked from the capture (:func:`choose_matcher`) unless ``sfm.matcher`` names one:

* exhaustive (every pair) up to ``sfm.exhaustive_max_images`` images;
* sequential for larger ordered captures (:func:`capture_order`: EXIF capture times, or names that
  number the images in sequence, as video frames and a camera's running numbers do): each image
  with its ``sfm.sequential_overlap`` successors and with those at power-of-two distances beyond,
  taken cyclically so that the end of a capture that walks around the object meets its start
  (:func:`sequential_pairs`);
* image retrieval with a vocabulary tree for larger unordered sets when ``sfm.vocab_tree_path``
  names a tree file (pycolmap does not ship one, and the stage downloads nothing); without one,
  exhaustive.

:class:`FeatureStore` extracts SIFT features and matches them into COLMAP databases in a work folder;
settings that share the feature settings share the features, and those that also share the
matching settings share the matches. Every extraction and matching is timed under its step name.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from rtsplat.config import SfmConfig
from rtsplat.errors import ConfigError
from rtsplat.io.images import capture_time
from rtsplat.sfm.stats import StepSeconds

_NUMBER = re.compile(r"^(.*?)(\d+)$")


@dataclass(frozen=True)
class CaptureOrder:
    """The images in the order they were taken, when the capture says so."""

    ordered: bool
    names: list[str]  # capture order when ordered, else name order
    reason: str


def capture_order(images_dir: Path, names: list[str]) -> CaptureOrder:
    """Whether the images form an ordered capture: EXIF capture times that tell them apart, or names
    with a common prefix and a running number (gaps of at most 3)."""
    times = {n: capture_time(images_dir / n) for n in names}
    timed = [n for n in names if times[n]]
    if len(names) >= 3 and len(timed) == len(names) and len(set(times.values())) >= 0.9 * len(names):
        order = sorted(names, key=lambda n: (times[n], n))
        return CaptureOrder(True, order, "the images' EXIF capture times order them")
    parts = [_NUMBER.match(Path(n).stem) for n in names]
    if len(names) >= 3 and all(parts) and len({p.group(1) for p in parts}) == 1:
        numbered = sorted(zip((int(p.group(2)) for p in parts), names, strict=True))
        gaps = [b[0] - a[0] for a, b in zip(numbered, numbered[1:], strict=False)]
        if all(1 <= g <= 3 for g in gaps):
            return CaptureOrder(True, [n for _, n in numbered], "the names number the images in sequence")
        return CaptureOrder(False, list(names), "the names' numbers skip (gaps above 3), and no EXIF capture times")
    return CaptureOrder(False, list(names), "neither EXIF capture times nor running numbers in the names")


def choose_matcher(cfg: SfmConfig, order: CaptureOrder) -> tuple[str, str]:
    """(matcher, why) for ``sfm.matcher``; ``auto`` decides from the number of images and their order."""
    n = len(order.names)
    if cfg.matcher == "vocabtree" or (cfg.matcher == "auto" and cfg.vocab_tree_path):
        if not cfg.vocab_tree_path or not Path(cfg.vocab_tree_path).is_file():
            raise ConfigError(
                f"sfm.vocab_tree_path {cfg.vocab_tree_path!r} is not a vocabulary tree file"
                + (" (sfm.matcher is vocabtree)" if cfg.matcher == "vocabtree" else ""),
                fix="set it to a COLMAP vocabulary tree file (e.g. vocab_tree_flickr100K_words32K.bin from the "
                "COLMAP downloads; nothing is downloaded here), or use sfm.matcher exhaustive or sequential",
            )
    if cfg.matcher != "auto":
        return cfg.matcher, f"sfm.matcher is {cfg.matcher}"
    pairs = n * (n - 1) // 2
    if n <= cfg.exhaustive_max_images:
        return "exhaustive", (
            f"{n} images, at most sfm.exhaustive_max_images {cfg.exhaustive_max_images}: all {pairs} pairs"
        )
    if order.ordered:
        count = len(sequential_pairs(order.names, cfg.sequential_overlap))
        return "sequential", (
            f"{n} images, more than sfm.exhaustive_max_images {cfg.exhaustive_max_images}, in capture order "
            f"({order.reason}): {count} neighbour pairs instead of {pairs}"
        )
    if cfg.vocab_tree_path:
        return "vocabtree", (
            f"{n} unordered images ({order.reason}), more than sfm.exhaustive_max_images "
            f"{cfg.exhaustive_max_images}: retrieval with the vocabulary tree {cfg.vocab_tree_path}"
        )
    return "exhaustive", (
        f"{n} unordered images ({order.reason}), more than sfm.exhaustive_max_images {cfg.exhaustive_max_images}, "
        f"but no vocabulary tree for retrieval (sfm.vocab_tree_path): all {pairs} pairs"
    )


def sequential_pairs(names: list[str], overlap: int) -> list[tuple[str, str]]:
    """Pairs of an ordered capture: each image with the next ``overlap`` images and with those at
    power-of-two distances beyond, distances taken around the end of the capture (cyclically)."""
    n = len(names)
    distances = set(range(1, min(overlap, n - 1) + 1))
    step = 1
    while step < n:
        if step > overlap:
            distances.add(step)
        step *= 2
    seen: set[tuple[int, int]] = set()
    for i in range(n):
        for d in sorted(distances):
            j = (i + d) % n
            if j != i:
                seen.add((min(i, j), max(i, j)))
    return [(names[i], names[j]) for i, j in sorted(seen)]


def _write_pairs(path: Path, pairs: Iterable[tuple[str, str]]) -> None:
    path.write_text("".join(f"{a} {b}\n" for a, b in pairs))


class FeatureStore:
    """SIFT features and matches of one image set in ``work``, reused between attempts and the refinement.

    ``settings`` of :meth:`features` / :meth:`matches` need ``features_key()``, ``guided_matching``
    and the SIFT fields (:class:`rtsplat.sfm.attempts.AttemptSettings`).
    """

    def __init__(
        self,
        images_dir: Path,
        order: CaptureOrder,
        work: Path,
        cfg: SfmConfig,
        mask_dir: Path | None,
        times: StepSeconds,
    ):
        self.images_dir = images_dir
        self.order = order
        self.names = sorted(order.names)
        self.work = work
        self.cfg = cfg
        self.mask_dir = mask_dir
        self.times = times
        self._features: dict[tuple, Path] = {}
        self._matches: dict[tuple, Path] = {}

    def features(self, s, step: str = "feature_extraction") -> Path:
        """A database with the features of ``s`` (extracted once per feature settings)."""
        import pycolmap

        key = s.features_key()
        if key in self._features:
            return self._features[key]
        db = self.work / f"features_{len(self._features)}.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = self.cfg.camera_model
        if self.mask_dir is not None:
            reader.mask_path = str(self.mask_dir)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = self.cfg.max_image_size
        extraction.num_threads = self.cfg.num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = s.max_num_features
        extraction.sift.peak_threshold = s.sift_peak_threshold
        extraction.sift.first_octave = s.sift_first_octave
        mode = pycolmap.CameraMode.SINGLE if self.cfg.single_camera else pycolmap.CameraMode.AUTO
        with self.times.step(step):
            pycolmap.extract_features(
                db,
                self.images_dir,
                image_names=self.names,
                camera_mode=mode,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        self._features[key] = db
        return db

    def _options(self, guided: bool):
        import pycolmap

        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = self.cfg.num_threads
        matching.guided_matching = guided
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = self.cfg.seed
        return matching, verification

    def matches(self, s, matcher: str) -> Path:
        """A database with the features of ``s`` matched by ``matcher`` (once per feature and matching settings)."""
        import pycolmap

        key = (*s.features_key(), matcher, s.guided_matching)
        if key in self._matches:
            return self._matches[key]
        features = self.features(s)
        db = self.work / f"matches_{len(self._matches)}.db"
        shutil.copyfile(features, db)
        matching, verification = self._options(s.guided_matching)
        cpu = pycolmap.Device.cpu
        with self.times.step("matching"):
            if matcher == "exhaustive":
                pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification, device=cpu)
            elif matcher == "sequential":
                pairs = self.work / f"pairs_{len(self._matches)}.txt"
                _write_pairs(pairs, sequential_pairs(self.order.names, self.cfg.sequential_overlap))
                pairing = pycolmap.ImportedPairingOptions()
                pairing.match_list_path = str(pairs)
                pycolmap.match_image_pairs(
                    db, matching_options=matching, pairing_options=pairing, verification_options=verification,
                    device=cpu,
                )
            elif matcher == "vocabtree":
                pairing = pycolmap.VocabTreePairingOptions()
                pairing.vocab_tree_path = str(self.cfg.vocab_tree_path)
                pairing.num_threads = self.cfg.num_threads
                pycolmap.match_vocabtree(
                    db, matching_options=matching, pairing_options=pairing, verification_options=verification,
                    device=cpu,
                )
            else:
                raise ValueError(f"unknown matcher {matcher!r}")
        self._matches[key] = db
        return db

    def existing_matches(self, s) -> Path | None:
        """A database already matched with the features and guided-matching setting of ``s``, if any."""
        for key, db in self._matches.items():
            if key[:-2] == s.features_key() and key[-1] == s.guided_matching:
                return db
        return None

    def matches_for_pairs(self, s, pairs: list[tuple[str, str]], step: str, feature_step: str) -> Path:
        """A new database with the features of ``s`` matched on ``pairs`` only."""
        import pycolmap

        features = self.features(s, feature_step)
        index = len(self._matches) + len(list(self.work.glob("pairs_*.txt")))
        db = self.work / f"pair_matches_{index}.db"
        shutil.copyfile(features, db)
        pair_file = self.work / f"pairs_{index}.txt"
        _write_pairs(pair_file, pairs)
        matching, verification = self._options(s.guided_matching)
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        with self.times.step(step):
            pycolmap.match_image_pairs(
                db, matching_options=matching, pairing_options=pairing, verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        return db

    def poorly_matched(
        self, s, matcher: str, names: list[str], min_inliers: int = 15, min_pairs: int = 2
    ) -> list[str]:
        """Of ``names``, those with fewer than ``min_pairs`` verified pairs of ``min_inliers`` inliers."""
        import pycolmap

        db = pycolmap.Database.open(str(self.matches(s, matcher)))
        try:
            ids = {im.image_id: im.name for im in db.read_all_images()}
            pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        finally:
            db.close()
        good = dict.fromkeys(ids.values(), 0)
        for pair_id, n in zip(pair_ids, inliers, strict=True):
            if n >= min_inliers:
                a, b = pycolmap.pair_id_to_image_pair(pair_id)
                good[ids[a]] += 1
                good[ids[b]] += 1
        return [n for n in names if good.get(n, 0) < min_pairs]


__all__ = ["CaptureOrder", "FeatureStore", "capture_order", "choose_matcher", "sequential_pairs"]
