"""What the workflow's input manifest costs: ``python -m rtsplat.bench.manifest <data>/<scene>``.

Times, on one scene folder, what every Snakemake invocation does per scene (:func:`refresh_manifest`
on an unchanged scene: one ``stat`` per file, the manifest read and compared) next to what a content
manifest would do instead (SHA-256 of every file's bytes), interleaved over ``--repeats`` rounds; the
median of each is printed. The second read of a file comes from the page cache, so the hash time is
a lower bound for files on a cold or network disk.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import tempfile
import time
from pathlib import Path

from rtsplat.io.manifest import refresh_manifest, scene_manifest


def hash_files(scene_dir: Path) -> dict[str, str]:
    """SHA-256 of every file the manifest lists."""
    root = Path(scene_dir).resolve()
    return {rel: hashlib.sha256((root / rel).read_bytes()).hexdigest() for rel in scene_manifest(root)["files"]}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene_dir", type=Path, help="a dataset scene folder (<data>/<scene>)")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)
    files = scene_manifest(args.scene_dir)["files"]
    images = sum(1 for rel in files if rel.startswith("images/"))
    size = sum(entry[0] for entry in files.values())
    stat_times, hash_times = [], []
    with tempfile.TemporaryDirectory() as tmp:
        path = refresh_manifest(args.scene_dir, Path(tmp) / "inputs.json")
        for _ in range(args.repeats):
            start = time.perf_counter()
            refresh_manifest(args.scene_dir, path)
            stat_times.append(time.perf_counter() - start)
            start = time.perf_counter()
            hash_files(args.scene_dir)
            hash_times.append(time.perf_counter() - start)
    print(f"{args.scene_dir}: {len(files)} files ({images} in images/), {size / 2**20:.1f} MiB")
    print(f"refresh_manifest (size + mtime, unchanged scene): {statistics.median(stat_times) * 1e3:.2f} ms")
    print(f"SHA-256 of every file (page cache warm):        {statistics.median(hash_times) * 1e3:.2f} ms")


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.manifest", main))
