"""The command line as a user meets it."""

import json
import subprocess
import sys
from pathlib import Path

from mowerhw import __version__
from mowerhw.cli import main

ROOT = Path(__file__).resolve().parent.parent


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "mowerhw", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )


def test_version_and_help():
    res = run("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"mowerhw {__version__}"
    res = run("--help")
    assert res.returncode == 0
    for word in ("config", "camera", "demo", "examples:"):
        assert word in res.stdout


def test_no_command_prints_help_and_exits_2(capsys):
    assert main([]) == 2
    assert "usage: mowerhw" in capsys.readouterr().out


def test_demo_json_reports_measured_figures():
    res = run("demo", "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    assert report["camera"]["model_check"]["project_vs_opencv_px_max"] < 1e-6
    assert report["camera"]["bearing_roundtrip_deg_max"] < 1e-6
    assert report["clocksync"]["mapped_error_ms_p99"] < 0.5
    assert report["buffer"]["time_ordered"] is True


def test_camera_info_json():
    res = run("camera", "info", "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    fov = report["field_of_view"]
    assert fov["elevation_min_deg"] < -40 and fov["elevation_max_deg"] > 30
    assert report["model_check"]["roundtrip_px_max"] < 1e-6


def test_camera_info_bad_calibration_exits_78(tmp_path):
    bad = tmp_path / "cam.yaml"
    bad.write_text("cam0:\n  camera_model: pinhole\n")
    res = run("camera", "info", "--calibration", str(bad))
    assert res.returncode == 78
    assert "cam0.camera_model: 'pinhole' is not supported" in res.stdout + res.stderr


def test_ctl_says_why_it_got_no_reply(tmp_path, capsys):
    """`mowerhw ctl` with no daemon, a daemon gone, and a daemon that does not answer (its
    estimation process stalled): each says which it is, not only the socket's errno."""
    import socket

    missing = tmp_path / "none.sock"
    assert main(["ctl", "--socket", str(missing), "status"]) == 1
    assert "no such socket: the daemon is not running" in capsys.readouterr().err
    assert main(["ctl", "--socket", str(missing), "supervisor"]) == 1
    out = capsys.readouterr()
    assert "the permit supervisor does not answer on" in out.err and "no such socket" in out.err
    assert json.loads(out.out)["ok"] is False  # strict JSON on stdout all the same

    gone = tmp_path / "gone.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.bind(str(gone))  # the file stays, nobody listens: a daemon that died
    assert main(["ctl", "--socket", str(gone), "status"]) == 1
    assert "nothing listens on it: the daemon is not running" in capsys.readouterr().err

    stalled = tmp_path / "stalled.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.bind(str(stalled))
        s.listen(1)  # accepted by the kernel, never answered
        assert main(["ctl", "--socket", str(stalled), "--timeout", "0.3", "status"]) == 1
    err = capsys.readouterr().err
    assert "no reply within 0.3 s: the daemon's estimation process is busy or stalled" in err
