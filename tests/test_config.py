"""One schema, validated at load: every kind of bad value gets a message naming it."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from mowerhw.config import (
    EX_CONFIG,
    Config,
    ConfigError,
    config_from_dict,
    config_to_dict,
    default_config,
    describe_schema,
    load_config,
)

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"


@pytest.mark.parametrize("name", ["mower.yaml", "bench.yaml"])
def test_shipped_configs_are_valid(name):
    cfg = load_config(CONFIGS / name)
    assert isinstance(cfg, Config)
    assert cfg.camera.calibration == (CONFIGS / "camera" / "paper-table1.yaml").resolve()
    assert cfg.source == CONFIGS / name


def test_mower_config_points_at_real_hardware():
    cfg = load_config(CONFIGS / "mower.yaml")
    assert (cfg.imu.driver, cfg.imu.port) == ("vn100", "/dev/ttyUSB0")
    assert (cfg.can.interface, cfg.can.channel) == ("socketcan", "can0")
    assert (cfg.camera.driver, cfg.camera.device) == ("v4l2", "/dev/video0")


def test_bench_config_points_at_mock_hardware():
    cfg = load_config(CONFIGS / "bench.yaml")
    assert cfg.imu.driver == "mock" and cfg.camera.driver == "mock"
    assert cfg.can.interface == "virtual"
    # the camera's liveness at its own 10 Hz: a limit under two of the front end's periods
    assert cfg.camera.camera_fps() == 10 and cfg.camera.fps == 4
    assert cfg.camera.stale_after_s < 2 / cfg.camera.fps


def test_defaults_and_round_trip():
    cfg = default_config()
    again = config_from_dict(config_to_dict(cfg))
    assert again == cfg
    assert cfg.imu.q_bi == (0.0, 1.0, 0.0, 0.0)


def _problems(tmp_path, doc, base_text=None):
    path = tmp_path / "cfg.yaml"
    path.write_text(base_text if base_text is not None else yaml.safe_dump(doc))
    # the calibration path is relative to the file: point it at the shipped one
    shutil.copytree(CONFIGS / "camera", tmp_path / "camera", dirs_exist_ok=True)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    return str(info.value), info.value.problems


BAD_VALUES = [
    (
        {"imu": {"baudrate": 12345}},
        "imu.baudrate: 12345 is not one of 9600, 19200, 38400, 57600, 115200, 128000, 230400, "
        "460800, 921600",
    ),
    ({"imu": {"driver": "vn200"}}, "imu.driver: 'vn200' is not one of vn100, mock"),
    (
        {"can": {"source_address": 0x80}, "speed": {"sensor_address": 0x80}},
        "speed.sensor_address: 0x80 is can.source_address, this ECU's own",
    ),
    (
        {"imu": {"rate_hz": 10}},
        "imu.stale_after_s: 0.1 s is under two sample periods at imu.rate_hz 10 (0.2 s)",
    ),
    (
        {"camera": {"fps": 1.5}},
        "camera.stale_after_s: 1 s is under two sample periods at camera.fps 1.5 (1.33333 s)",
    ),
    (
        {"camera": {"device_fps": 2}},
        "camera.device_fps: 2 is under camera.fps 4: the front end cannot track more frames",
    ),
    (
        {"camera": {"device_fps": 10, "stale_after_s": 0.15}},
        "camera.stale_after_s: 0.15 s is under two sample periods at camera.device_fps 10 (0.2 s)",
    ),
    (
        {"camera": {"stale_after_s": 0.25}},
        "camera.stale_after_s: 0.25 s is under two sample periods at camera.fps 4 (0.5 s)",
    ),
    (
        {"frontend": {"klt_base_level": 2, "klt_levels": 1}},
        "frontend.klt_base_level: 2 is above frontend.klt_levels (1)",
    ),
    (
        {"frontend": {"subpixel": False}},
        "frontend.klt_base_level: 1 needs frontend.subpixel: true",
    ),
    ({"imu": {"rate_hz": 99}}, "imu.rate_hz: 99 is not one of 1, 2, 4, 5, 8, 10, 16, 20, 25"),
    ({"imu": {"rate_hz": "fast"}}, "imu.rate_hz: 'fast' is not a whole number"),
    ({"imu": {"rate_hz": 100.5}}, "imu.rate_hz: 100.5 is not a whole number"),
    ({"imu": {"stale_after_s": 0}}, "imu.stale_after_s: 0 is out of range: must be greater than 0"),
    ({"imu": {"stale_after_s": -1.5}}, "imu.stale_after_s: -1.5 is out of range"),
    ({"imu": {"stale_after_s": ".nan"}}, "imu.stale_after_s: '.nan' is not a number"),
    ({"imu": {"low_latency": "yes please"}}, "imu.low_latency: 'yes please' is not true or false"),
    ({"imu": {"low_latency": 1}}, "imu.low_latency: 1 is not true or false"),
    ({"imu": {"port": ""}}, "imu.port: must not be empty"),
    ({"imu": {"port": 5}}, "imu.port: 5 is not a string"),
    ({"imu": {"q_bi": [1, 0, 0]}}, "imu.q_bi: [1, 0, 0] must be a list of 4 numbers"),
    ({"imu": {"q_bi": [1, 1, 0, 0]}}, "imu.q_bi: [1.0, 1.0, 0.0, 0.0] is not a unit quaternion"),
    ({"imu": {"q_bi": [1, "x", 0, 0]}}, "imu.q_bi[1]: 'x' is not a number"),
    ({"imu": {"baudrat": 9600}}, "imu.baudrat: unknown key (did you mean 'baudrate'?)"),
    ({"imus": {}}, "imus: unknown key (did you mean 'imu'?); allowed keys: imu, can, speed"),
    ({"imu": [1, 2]}, "imu: expected a mapping of keys, got [1, 2]"),
    ({"can": {"bitrate": 300000}}, "can.bitrate: 300000 is not one of 125000, 250000, 500000"),
    ({"can": {"interface": "socketcann"}}, "can.interface: 'socketcann' is not one of socketcan"),
    (
        {"can": {"source_address": 254}},
        "can.source_address: 254 is out of range: must be at most 253",
    ),
    ({"can": {"source_address": True}}, "can.source_address: True is not a whole number"),
    ({"speed": {"sensor_address": -1}}, "speed.sensor_address: -1 is out of range"),
    ({"camera": {"calibration": "nowhere.yaml"}}, "camera.calibration: "),
    (
        {"camera": {"width": 640}},
        "camera.width/height: 640x1540 does not match the calibration's resolution 1540x1540",
    ),
    ({"camera": {"fps": 0}}, "camera.fps: 0 is out of range: must be greater than 0"),
    (
        {"camera": {"timestamps": "gps"}},
        "camera.timestamps: 'gps' is not one of auto, monotonic, device, arrival",
    ),
    ({"permit": {"period_s": 1.0}}, "permit.period_s: 1 is out of range: must be at most 0.1"),
    ({"permit": {"status_pgn": 0xFE49}}, "permit.status_pgn: 65097 is out of range"),
    ({"teach": {"gamma1": 0.5}}, "teach.gamma1: 0.5 is out of range: must be less than 0"),
    ({"mow": {"gate_probability": 1.0}}, "mow.gate_probability: 1 is out of range"),
    ({"containment": {"soft_persist": 0}}, "containment.soft_persist: 0 is out of range"),
    ({"runtime": {"mode": "mowing"}}, "runtime.mode: 'mowing' is not one of idle, teach, mow"),
    (
        {"imu": {"output": "ascii", "baudrate": 115200}},
        "imu.baudrate: 115200 is too slow for 100 Hz ASCII output",
    ),
]


@pytest.mark.parametrize(("doc", "expected"), BAD_VALUES)
def test_bad_values_are_named_with_what_is_allowed(tmp_path, doc, expected):
    message, problems = _problems(tmp_path, doc)
    assert expected in message, message
    assert len(problems) == 1
    assert message.startswith(str(tmp_path / "cfg.yaml") + ": ")


def test_every_problem_is_reported_at_once(tmp_path):
    _, problems = _problems(tmp_path, {"imu": {"baudrate": 1, "rate_hz": 3}, "can": {"x": 1}})
    assert len(problems) == 3


def test_invalid_yaml_says_where(tmp_path):
    message, _ = _problems(tmp_path, None, base_text="imu:\n  baudrate: [921600\n")
    assert "not valid YAML at line" in message


def test_top_level_must_be_a_mapping(tmp_path):
    message, _ = _problems(tmp_path, None, base_text="- imu\n- can\n")
    assert "top level: expected a mapping of keys" in message


def test_missing_file():
    with pytest.raises(ConfigError, match="file not found"):
        load_config("/nonexistent/mowerhw.yaml")


def test_empty_file_means_defaults(tmp_path):
    (tmp_path / "empty.yaml").write_text("")
    cfg = load_config(tmp_path / "empty.yaml")
    assert cfg.imu == default_config().imu
    # a relative default names the shipped file, wherever the config lives
    assert cfg.camera.calibration == (CONFIGS / "camera" / "paper-table1.yaml").resolve()


def test_explicit_relative_paths_are_relative_to_the_file(tmp_path):
    (tmp_path / "cal").mkdir()
    shutil.copy(CONFIGS / "camera" / "paper-table1.yaml", tmp_path / "cal" / "mine.yaml")
    (tmp_path / "c.yaml").write_text("camera:\n  calibration: cal/mine.yaml\n")
    assert load_config(tmp_path / "c.yaml").camera.calibration == tmp_path / "cal" / "mine.yaml"


def test_schema_lists_every_section():
    text = "\n".join(describe_schema())
    for key in (
        "imu.baudrate",
        "can.channel",
        "speed.stale_after_s",
        "camera.calibration",
        "teach.gamma1",
        "mow.gate_probability",
        "containment.margin_m",
        "map.path",
    ):
        assert key in text


def _cli(*args, cwd=ROOT):
    return subprocess.run(
        [sys.executable, "-m", "mowerhw", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
    )


def test_config_check_exit_codes(tmp_path):
    ok = _cli("config", "check", "configs/mower.yaml")
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("imu:\n  baudrate: 12345\n")
    res = _cli("config", "check", str(bad))
    assert res.returncode == EX_CONFIG
    assert "imu.baudrate: 12345 is not one of 9600, 19200" in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("command", [["demo"], ["camera", "info"], ["config", "show"]])
def test_every_command_with_config_exits_78_on_a_bad_file(tmp_path, command):
    bad = tmp_path / "bad.yaml"
    bad.write_text("can:\n  bitrate: fast\n")
    res = _cli(*command, "--config", str(bad))
    assert res.returncode == EX_CONFIG, res.stdout + res.stderr
    assert "can.bitrate: 'fast' is not a whole number" in res.stderr
