"""The scene input manifest: rewritten exactly when a file under the scene changed."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from rtsplat.io.manifest import refresh_manifest, scene_manifest


def _scene(tmp_path):
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "sparse" / "0").mkdir(parents=True)
    for i in range(3):
        (scene / "images" / f"{i:04d}.png").write_bytes(bytes([i]) * (100 + i))
    (scene / "sparse" / "0" / "cameras.bin").write_bytes(b"cams")
    (scene / ".DS_Store").write_bytes(b"finder")
    (scene / "images" / ".hidden").mkdir()
    (scene / "images" / ".hidden" / "x.png").write_bytes(b"x")
    return scene


def test_manifest_lists_every_visible_file_with_size_and_mtime(tmp_path):
    scene = _scene(tmp_path)
    files = scene_manifest(scene)["files"]
    assert sorted(files) == ["images/0000.png", "images/0001.png", "images/0002.png", "sparse/0/cameras.bin"]
    st = (scene / "images" / "0002.png").stat()
    assert files["images/0002.png"] == [102, st.st_mtime_ns]


def test_refresh_rewrites_only_when_a_file_changed(tmp_path):
    scene = _scene(tmp_path)
    image = scene / "images" / "0001.png"
    os.utime(image, ns=(2_000_000_000, 2_000_000_000))  # written long ago: the edit below changes its mtime
    path = refresh_manifest(scene, tmp_path / "results" / "inputs.json")
    os.utime(path, ns=(1_000_000_000, 1_000_000_000))  # an old manifest: any rewrite is visible
    refresh_manifest(scene, path)
    assert path.stat().st_mtime_ns == 1_000_000_000  # nothing changed: left as it was
    (scene / ".DS_Store").write_bytes(b"finder, again")
    refresh_manifest(scene, path)
    assert path.stat().st_mtime_ns == 1_000_000_000  # hidden files do not count

    with open(image, "r+b") as f:  # edited in place: the folder's mtime stays, the file's does not
        f.write(b"\xff")
    refresh_manifest(scene, path)
    assert path.stat().st_mtime_ns > 1_000_000_000
    assert json.loads(path.read_text())["files"]["images/0001.png"][1] == image.stat().st_mtime_ns

    os.utime(path, ns=(1_000_000_000, 1_000_000_000))
    os.utime(image, ns=(3_000_000_000, 3_000_000_000))  # an older copy put back (cp -p, rsync -t)
    refresh_manifest(scene, path)
    assert path.stat().st_mtime_ns > 1_000_000_000

    os.utime(path, ns=(1_000_000_000, 1_000_000_000))
    (scene / "images" / "0002.png").unlink()  # a view removed
    refresh_manifest(scene, path)
    assert path.stat().st_mtime_ns > 1_000_000_000
    assert "images/0002.png" not in json.loads(path.read_text())["files"]


def test_an_unreadable_manifest_is_rewritten(tmp_path):
    scene = _scene(tmp_path)
    path = tmp_path / "inputs.json"
    path.write_text("{truncated")
    refresh_manifest(scene, path)
    assert json.loads(path.read_text()) == scene_manifest(scene)


def test_content_fingerprints_follow_contents_not_paths(tmp_path):
    from rtsplat.io.manifest import FINGERPRINT_SAMPLE, file_fingerprint, folder_fingerprint

    scene = _scene(tmp_path)
    big = scene / "images" / "big.png"
    data = bytearray(range(256)) * (3 * FINGERPRINT_SAMPLE // 256)  # 192 KiB: ends sampled, middle not
    big.write_bytes(bytes(data))
    first = folder_fingerprint(scene)
    copy = tmp_path / "elsewhere" / "scene"
    shutil.copytree(scene, copy)
    assert folder_fingerprint(copy) == first  # moved or copied: same contents, same fingerprint

    for offset, seen in ((0, True), (len(data) - 1, True), (len(data) // 2, False)):
        changed = bytearray(data)
        changed[offset] ^= 0xFF
        big.write_bytes(bytes(changed))
        assert (file_fingerprint(big) != file_fingerprint(copy / "images" / "big.png")) is seen, offset
        assert (folder_fingerprint(scene) != first) is seen, offset
    big.write_bytes(bytes(data))
    (scene / "images" / "0001.png").rename(scene / "images" / "0001b.png")  # a renamed file
    assert folder_fingerprint(scene) != first


def test_made_from_other_photos_is_refused_naming_both(tmp_path):
    from rtsplat.errors import PipelineError
    from rtsplat.io.manifest import check_made_from_photos, photo_fingerprints

    scene = _scene(tmp_path)
    photos = photo_fingerprints(scene / "images")
    assert sorted(photos) == ["0000.png", "0001.png", "0002.png"]
    summary = {"photos": dict(photos), "scene_dir": str(scene)}
    check_made_from_photos(tmp_path / "sfm", summary, "sfm", scene / "images", photos, "--sfm")  # passes
    check_made_from_photos(tmp_path / "sfm", {}, "sfm", scene / "images", photos, "--sfm")  # no record: passes

    (scene / "images" / "0001.png").write_bytes(b"edited")
    (scene / "images" / "0002.png").unlink()
    (scene / "images" / "0003.png").write_bytes(b"new")
    now = photo_fingerprints(scene / "images")
    with pytest.raises(PipelineError) as info:
        check_made_from_photos(tmp_path / "sfm", summary, "sfm", scene / "images", now, "--sfm")
    assert "0001.png (changed), 0003.png (added), 0002.png (removed)" in str(info.value)

    other = {"a.jpg": "0" * 16, "b.jpg": "1" * 16}
    with pytest.raises(PipelineError) as info:
        check_made_from_photos(tmp_path / "masks", {"photos": other, "scene_dir": "/data/b"}, "masks",
                               scene / "images", now, "--masks")
    assert "belongs to other photos" in str(info.value) and "/data/b" in str(info.value)
    assert str(scene / "images") in str(info.value)


def test_a_project_copied_elsewhere_keeps_its_manifest(tmp_path):
    """Copied with the files' modification times (cp -a, rsync -a), a project's manifests stay as
    they are: they hold no absolute paths, so nothing reruns."""
    import shutil

    project = tmp_path / "project"
    scene = _scene(project / "data")
    path = refresh_manifest(scene, project / "results" / "scene" / "inputs.json")
    assert str(tmp_path) not in path.read_text()
    copy = tmp_path / "elsewhere"
    shutil.copytree(project, copy)  # copy2: modification times kept
    copied = copy / "results" / "scene" / "inputs.json"
    os.utime(copied, ns=(1_000_000_000, 1_000_000_000))
    refresh_manifest(copy / "data" / "scene", copied)
    assert copied.stat().st_mtime_ns == 1_000_000_000
