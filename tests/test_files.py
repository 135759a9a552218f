import json
import os

import pytest

from beadsight.files import (
    WriteError,
    atomic_write_bytes,
    atomic_write_json,
    finish_partial,
    partial_path,
    remove_stale_temps,
)


def test_atomic_write_replaces_and_leaves_no_temp(tmp_path):
    target = tmp_path / "sub" / "a.json"
    atomic_write_json(target, {"x": 1})
    atomic_write_json(target, {"x": 2})
    assert json.loads(target.read_text()) == {"x": 2}
    assert sorted(p.name for p in target.parent.iterdir()) == ["a.json"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_strict_json_refuses_nan_and_keeps_the_old_file(tmp_path):
    target = tmp_path / "m.json"
    atomic_write_json(target, {"ok": 1})
    with pytest.raises(ValueError):
        atomic_write_json(target, {"bad": float("nan")}, strict=True)
    assert json.loads(target.read_text()) == {"ok": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]


def test_full_disk_is_a_named_error_and_the_old_file_survives(full_disk):
    target = full_disk / "model.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(WriteError, match=r"model\.bin.*disk full"):
        atomic_write_bytes(target, b"x" * (1 << 20))
    assert target.read_bytes() == b"old"
    assert [p.name for p in full_disk.iterdir()] == ["model.bin"]


def test_partial_file_is_renamed_only_when_finished(tmp_path):
    final = tmp_path / "rec.h5"
    partial = partial_path(final)
    assert partial.name == "rec.h5.partial"
    partial.write_bytes(b"data")
    assert not final.exists()
    finish_partial(partial, final)
    assert final.read_bytes() == b"data" and not partial.exists()


def test_stale_temps_are_removed(tmp_path):
    (tmp_path / ".best.pt.abc123.tmp").write_bytes(b"torn")
    (tmp_path / "best.pt").write_bytes(b"good")
    removed = remove_stale_temps(tmp_path, "best.pt")
    assert [p.name for p in removed] == [".best.pt.abc123.tmp"]
    assert [p.name for p in tmp_path.iterdir()] == ["best.pt"]
