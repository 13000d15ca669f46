"""Crash-safe file writing (mowerhw/common/fileio.py)."""

import os
import stat

import pytest

from mowerhw.common.fileio import write_atomic


@pytest.mark.parametrize("durable", [True, False])
def test_write_atomic_replaces_the_file_whole(tmp_path, durable):
    """The new bytes replace the old, the folder is made if missing, the mode is the one
    asked for whatever the umask, and no temporary file is left behind."""
    path = tmp_path / "sub" / "pose.json"
    old = os.umask(0o077)
    try:
        write_atomic(path, b"first", durable=durable)
        write_atomic(path, b"second, longer", mode=0o640, durable=durable)
    finally:
        os.umask(old)
    assert path.read_bytes() == b"second, longer"
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert sorted(p.name for p in path.parent.iterdir()) == ["pose.json"]


def test_a_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / "pose.json"
    write_atomic(path, b"good", durable=False)
    with pytest.raises(TypeError):
        write_atomic(path, "not bytes", durable=False)  # type: ignore[arg-type]
    assert path.read_bytes() == b"good"
    assert [p.name for p in tmp_path.iterdir()] == ["pose.json"]
