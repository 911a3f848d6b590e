"""rtsplat.io.atomic: outputs appear whole or not at all."""

import json
import os

import pytest

from rtsplat.io.atomic import atomic_dir, atomic_file, write_bytes_atomic, write_json_atomic, write_text_atomic


def test_files_are_written_whole_with_plain_permissions(tmp_path):
    write_text_atomic(tmp_path / "a" / "t.txt", "hé\n")
    write_bytes_atomic(tmp_path / "b.bin", b"\x00\xff")
    write_json_atomic(tmp_path / "c.json", {"z": 1, "a": [1.5]})
    assert (tmp_path / "a" / "t.txt").read_text(encoding="utf-8") == "hé\n"
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\xff"
    assert (tmp_path / "c.json").read_text() == '{\n  "z": 1,\n  "a": [\n    1.5\n  ]\n}\n'
    assert json.loads((tmp_path / "c.json").read_text()) == {"z": 1, "a": [1.5]}
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o666 & ~umask
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b.bin", "c.json"]


@pytest.mark.parametrize("existing", [False, True])
def test_a_failure_inside_leaves_neither_target_nor_temporary(tmp_path, existing):
    target = tmp_path / "out.ply"
    if existing:
        target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="boom"), atomic_file(target, "wb") as fh:
        fh.write(b"half a file")
        raise RuntimeError("boom")
    assert [p.name for p in tmp_path.iterdir()] == (["out.ply"] if existing else [])
    if existing:
        assert target.read_bytes() == b"old"


def test_atomic_file_only_creates_new_files(tmp_path):
    with pytest.raises(ValueError, match="mode"), atomic_file(tmp_path / "x", "a"):
        pass
    assert list(tmp_path.iterdir()) == []


def test_atomic_dir_replaces_only_on_success(tmp_path):
    final = tmp_path / "result"
    with atomic_dir(final) as tmp:
        (tmp / "one").write_text("1")
    with pytest.raises(RuntimeError), atomic_dir(final) as tmp:
        (tmp / "two").write_text("2")
        raise RuntimeError("boom")
    assert [p.name for p in final.iterdir()] == ["one"]
    assert [p.name for p in tmp_path.iterdir()] == ["result"]
    with atomic_dir(final) as tmp:
        (tmp / "three").write_text("3")
    assert [p.name for p in final.iterdir()] == ["three"]
    assert [p.name for p in tmp_path.iterdir()] == ["result"]
