"""The pose saved for a restart (docs/design.md §8): its age by a clock that does not step."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mowerhw.runtime.mapfiles import RESUME_MAX_AGE_S, PoseFile
from mowerhw.runtime.pipelines import StartPose

MAP = SimpleNamespace(checksum="c0ffee")


def _saved(tmp_path: Path, **change: Any) -> PoseFile:
    """A pose saved now, then its file's fields changed as ``change`` says."""
    pf = PoseFile(tmp_path / "pose.json")
    pf.save(StartPose(np.array([3.0, -2.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])), "c0ffee")
    doc = json.loads(pf.path.read_text())
    doc.update(change)
    pf.path.write_text(json.dumps(doc))
    return pf


def test_a_pose_saved_just_now_is_resumed(tmp_path: Path) -> None:
    got = _saved(tmp_path).load(MAP)  # type: ignore[arg-type]
    assert got is not None
    np.testing.assert_allclose(got.position, [3.0, -2.0, 0.0])


def test_within_a_boot_the_age_ignores_a_wall_clock_step(tmp_path: Path) -> None:
    """NTP's first sync steps a clock-less mower computer's wall clock by hours: a pose saved
    seconds ago still resumes, and one from long ago in this boot does not, whatever the wall
    clock says."""
    stepped = _saved(tmp_path, wall_time=time.time() - 3 * 3600.0)
    assert stepped.load(MAP) is not None  # type: ignore[arg-type]
    old = _saved(
        tmp_path,
        wall_time=time.time() - 5.0,
        boot_time=time.clock_gettime(time.CLOCK_BOOTTIME) - 2 * RESUME_MAX_AGE_S,
    )
    assert old.load(MAP) is None  # type: ignore[arg-type]


def test_across_a_reboot_the_wall_clock_judges(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    other = "00000000-0000-0000-0000-000000000000"
    fresh = _saved(tmp_path, boot_id=other, boot_time=1e9, wall_time=time.time() - 10.0)
    assert fresh.load(MAP) is not None  # type: ignore[arg-type]
    stale = _saved(tmp_path, boot_id=other, boot_time=1.0, wall_time=time.time() - 1000.0)
    with caplog.at_level(logging.INFO, "mowerhw.daemon"):
        assert stale.load(MAP) is None  # type: ignore[arg-type]
    assert "saved 1000" in caplog.text and "the wall clock (saved before a reboot)" in caplog.text


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"map_checksum": "beef"}, "saved on another map"),
        ({"quaternion": [0.0, 0.0, 0.0, 0.0]}, "not finite or not a rotation"),
        ({"position": [1.0, 2.0]}, "unreadable"),
        ({"boot_time": "soon"}, "unreadable"),
    ],
)
def test_a_pose_that_cannot_be_trusted_is_not_resumed_and_the_log_says_why(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, change: dict[str, Any], why: str
) -> None:
    with caplog.at_level(logging.INFO, "mowerhw.daemon"):
        assert _saved(tmp_path, **change).load(MAP) is None  # type: ignore[arg-type]
    assert why in caplog.text


def test_a_missing_or_garbled_file_is_no_pose(tmp_path: Path) -> None:
    pf = PoseFile(tmp_path / "pose.json")
    assert pf.load(MAP) is None  # type: ignore[arg-type]
    pf.path.write_bytes(b"\x00garbage")
    assert pf.load(MAP) is None  # type: ignore[arg-type]
    pf.path.write_text("[1, 2]")
    assert pf.load(MAP) is None  # type: ignore[arg-type]


def test_the_gyro_bias_is_resumed_within_the_boot_only(tmp_path: Path) -> None:
    """The bias the previous run had learnt comes back with its pose within the same boot
    (the IMU stayed on); across a reboot, or garbled, the pose comes back without it (the
    gyro is calibrated again while the mower stands)."""
    pf = PoseFile(tmp_path / "pose.json")
    bias = np.array([0.001, -0.002, 0.0005])
    pf.save(StartPose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), bias), "c0ffee")
    got = pf.load(MAP)  # type: ignore[arg-type]
    assert got is not None and got.gyro_bias is not None
    np.testing.assert_allclose(got.gyro_bias, bias)
    doc = json.loads(pf.path.read_text())
    for change in (
        {"boot_id": "00000000-0000-0000-0000-000000000000", "wall_time": time.time()},
        {"gyro_bias": [5.0, 0.0, 0.0]},
    ):
        pf.path.write_text(json.dumps({**doc, **change}))
        got = pf.load(MAP)  # type: ignore[arg-type]
        assert got is not None and got.gyro_bias is None
    pf.path.write_text(json.dumps({**doc, "gyro_bias": [1.0, 2.0]}))
    assert pf.load(MAP) is None  # type: ignore[arg-type]  # unreadable: the log says so
