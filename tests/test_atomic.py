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


def test_torch_save_onto_a_full_disk_says_no_space_and_leaves_nothing(tmp_path, monkeypatch):
    """torch.save reports a failed write as RuntimeError 'unexpected pos'; the OSError behind it names
    the cause. /dev/full fails every write with ENOSPC, like a full disk."""
    torch = pytest.importorskip("torch")
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    from rtsplat.errors import PipelineError

    target = tmp_path / "last.pt"
    target.write_bytes(b"the previous checkpoint")
    real_open = os.open
    monkeypatch.setattr(os, "open", lambda path, flags, *a: real_open("/dev/full", os.O_WRONLY)
                        if ".last.pt.tmp-" in str(path) else real_open(path, flags, *a))
    with pytest.raises(PipelineError, match="no space left on device") as info, atomic_file(target, "wb") as fh:
        torch.save({"x": torch.zeros(100000)}, fh)
    assert info.value.path == str(target)
    chain, error = [], info.value
    while error is not None:
        chain.append(str(error))
        error = error.__cause__ or error.__context__
    assert any("unexpected pos" in text for text in chain)  # torch's own report of the failed write
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"] and target.read_bytes() == b"the previous checkpoint"


def test_a_library_error_on_a_nearly_full_disk_is_named_as_one(tmp_path, monkeypatch):
    """A RuntimeError that lost its OSError counts as a full disk only when the disk is nearly full."""
    import shutil

    from rtsplat.errors import PipelineError
    from rtsplat.io import atomic

    with pytest.raises(RuntimeError, match="lost"), atomic_file(tmp_path / "a.bin", "wb"):
        raise RuntimeError("lost")
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda path: usage._replace(free=4096))
    with pytest.raises(PipelineError, match="no space left on device, 4.0 KiB free"), \
            atomic_file(tmp_path / "a.bin", "wb"):
        raise RuntimeError("lost")
    with pytest.raises(ValueError), atomic_file(tmp_path / "a.bin", "wb"):  # not a library's write error
        raise ValueError("bad value")
    assert list(tmp_path.iterdir()) == []


def test_read_errors_of_inputs_pass_unchanged(tmp_path):
    """An OSError about a file that is not the output (an input read inside the block) is not a write failure."""
    with pytest.raises(PermissionError), atomic_dir(tmp_path / "out"):
        raise PermissionError(13, "Permission denied", str(tmp_path / "input.png"))
    assert list(tmp_path.iterdir()) == []
