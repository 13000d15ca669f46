"""Configs and maps written by an attacker or a careless user (issue 16): every one refused
with a message naming the problem, never a traceback, never accepted when dangerous."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mowerhw.config import ConfigError, config_from_dict, load_config
from mowerhw.map import LawnMap, MapError, _digest, from_document, load
from mowerhw.runtime.mapfiles import load_map_isolated

# ------------------------------------------------------------------------------------ configs

#: the six values that together gave 62 missed halts in a 200 s `sim mow`, each alone
DANGEROUS = [
    ({"containment": {"k_sigma": 0}}, "containment.k_sigma: 0 is out of range: must be at least 2"),
    (
        {"containment": {"sigma_max_m": 1e9}},
        "containment.sigma_max_m: 1000000000 is out of range: must be at most 0.5",
    ),
    (
        {"containment": {"hard_margin_m": 1e9}},
        "containment.hard_margin_m: 1000000000 is out of range: must be at most 0.3",
    ),
    (
        {"containment": {"soft_persist": 100}},
        "containment.soft_persist: 100 is out of range: must be at most 10",
    ),
    (
        {"containment": {"margin_m": 0}},
        "containment.margin_m: 0 is out of range: must be at least 0.1",
    ),
    (
        {"mow": {"max_dead_reckoning_s": 60}},
        "mow.max_dead_reckoning_s: 60 is out of range: must be at most 10",
    ),
    (
        {"runtime": {"fault_injection": True}},
        "runtime.fault_injection: only for the test bench (can.interface virtual or "
        "udp_multicast), not with can.interface 'socketcan'",
    ),
    (
        {"runtime": {"socket_mode": 0o777}},
        "runtime.socket_mode: 0o777 is out of range: must be at most 0o770",
    ),
    ({"runtime": {"socket_mode": 0o606}}, "runtime.socket_mode: 0o606 lets every user"),
]


@pytest.mark.parametrize(("raw", "message"), DANGEROUS)
def test_dangerous_config_values_are_refused(tmp_path: Path, raw: dict, message: str) -> None:
    raw = copy.deepcopy(raw)
    raw.setdefault("runtime", {}).setdefault("control_socket", str(tmp_path / "c.sock"))
    raw["runtime"].setdefault("pose_file", str(tmp_path / "pose.json"))
    with pytest.raises(ConfigError) as err:
        config_from_dict(raw)
    assert message in str(err.value)


def test_colliding_and_occupied_paths_are_refused(tmp_path: Path) -> None:
    m = tmp_path / "lawn.json"
    with pytest.raises(ConfigError, match=r"runtime.control_socket: .* is also map.path"):
        config_from_dict({"map": {"path": str(m)}, "runtime": {"control_socket": str(m)}})
    with pytest.raises(ConfigError, match=r"runtime.control_socket: .* is a directory"):
        config_from_dict({"runtime": {"control_socket": str(tmp_path)}})
    m.write_text("{}")
    with pytest.raises(ConfigError, match="is a file that is not a socket"):
        config_from_dict({"runtime": {"control_socket": str(m)}})
    with pytest.raises(ConfigError, match=r"runtime.pose_file: .* is also map.path"):
        config_from_dict({"map": {"path": str(m)}, "runtime": {"pose_file": str(m)}})


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "a: &a [x, x, x, x]\nb: &b [*a, *a, *a]\nc: [*b, *b, *b]\n",
            "aliases (*name) are not allowed",
        ),
        ("imu: " + "[" * 200 + "]" * 200 + "\n", "nested more than 16 levels deep"),
        ("imu: {rate_hz: 1" + "0" * 5000 + "}\n", "not a usable YAML value"),
        (
            "imu: {rate_hz: [" + "1, " * 100_000 + "]}\n",
            "imu.rate_hz: [1, 1, 1, 1, 1, 1, ...] is not",
        ),
        ("{{{{", "not valid YAML"),
        (  # PyYAML alone keeps the second silently
            "camera:\n  fps: 4\n  fps: 30\n",
            "at line 3, column 3: the key 'fps' is given twice (first on line 2)",
        ),
        ("imu: {}\ncan: {}\nimu: {rate_hz: 10}\n", "the key 'imu' is given twice"),
    ],
)
def test_hostile_yaml_is_refused_without_running_out_of_anything(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert message in str(err.value)
    assert len(str(err.value)) < 2000


def test_a_config_that_is_not_a_file_or_too_big_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(tmp_path)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (1 << 20) + "\n")
    with pytest.raises(ConfigError, match="larger than 1048576 bytes"):
        load_config(big)


config_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats()
    | st.text(max_size=12)
    | st.sampled_from(["0o777", "1e9", "-0", "nan", "/dev/zero", "virtual"]),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
SECTIONS = ["imu", "can", "speed", "camera", "permit", "frontend", "teach", "mow", "containment"]
KEYS = ["rate_hz", "k_sigma", "margin_m", "port", "fps", "interface", "sigma_max_m", "q_bi", "x"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.dictionaries(
        st.sampled_from(SECTIONS),
        st.dictionaries(st.sampled_from(KEYS), config_values, max_size=3) | config_values,
        max_size=3,
    )
)
def test_fuzzed_configs_load_or_fail_with_messages(raw: dict[str, Any]) -> None:
    try:
        cfg = config_from_dict(raw)
    except ConfigError as exc:
        assert exc.problems and all(isinstance(p, str) and p for p in exc.problems)
        return
    c = cfg.containment  # whatever got through keeps the containment bounds
    assert c.k_sigma >= 2 and c.sigma_max_m <= 0.5 and c.soft_persist <= 10


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300))
def test_fuzzed_yaml_text_loads_or_fails_with_a_message(tmp_path_factory: Any, text: str) -> None:
    path = tmp_path_factory.mktemp("cfg") / "c.yaml"
    path.write_text(text)
    try:
        load_config(path)
    except ConfigError as exc:
        assert str(exc)


# --------------------------------------------------------------------------------------- maps


@pytest.fixture(scope="module")
def good_map_doc() -> dict[str, Any]:
    rng = np.random.default_rng(3)
    from mowerhw.map import Landmark

    lms = [Landmark(i, rng.uniform(-5, 5, 3), np.eye(3) * 1e-4, None, None) for i in range(8)]
    boundary = np.array([[0, 0], [10, 0], [10, 8], [0, 8]], float)
    doc: dict[str, Any] = LawnMap(boundary=boundary, landmarks=lms).to_document()
    return doc


def _signed(doc: dict[str, Any]) -> dict[str, Any]:
    doc = copy.deepcopy(doc)
    doc.pop("checksum", None)
    try:
        doc["checksum"] = "sha256:" + _digest(doc)
    except ValueError:  # NaN in it: no checksum can be made, the map is refused for it
        doc["checksum"] = "sha256:0"
    return doc


def _with(doc: dict[str, Any], edit: Any) -> dict[str, Any]:
    doc = copy.deepcopy(doc)
    edit(doc)
    return _signed(doc)


MAP_EDITS = [
    (
        lambda d: d["landmarks"][0].update(covariance=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]]),
        "landmarks[0].covariance: not positive semi-definite",
    ),
    (
        lambda d: d["landmarks"][0].update(covariance=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]),
        "landmarks[0].covariance: not symmetric",
    ),
    (
        lambda d: d["areas"][0].update(
            polygon=[[x * 1e150, y * 1e150] for x, y in d["areas"][0]["polygon"]]
        ),
        "area 'lawn': coordinates beyond ±10000 m",
    ),
    (lambda d: d["landmarks"][0].update(id=2**63), "needs an integer id from 0 to 2**63 - 1"),
    (lambda d: d["landmarks"][0].update(id=-1), "needs an integer id from 0 to 2**63 - 1"),
    (
        lambda d: d.update(keepout_zones=[{"name": "all", "polygon": d["areas"][0]["polygon"]}]),
        "keep-outs: they leave 0.0 m² to mow",
    ),
    (lambda d: d["landmarks"][0].update(xyz=[1e300, 0, 0]), "landmarks[0].xyz: values beyond"),
    (lambda d: d["landmarks"][0].update(keyframe=True), "keyframe: must be null or an integer"),
    (lambda d: d.update(landmarks={"a": 1}), "landmarks must be a list"),
]


@pytest.mark.parametrize(("edit", "message"), MAP_EDITS)
def test_wrong_maps_are_refused_by_name(good_map_doc: dict, edit: Any, message: str) -> None:
    with pytest.raises(MapError) as err:
        from_document(_with(good_map_doc, edit))
    assert message in str(err.value)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"[" * 100_000, "JSON nested too deeply"),
        (b'{"a": 1' + b"0" * 5000 + b"}", "an integer of 5001 digits; at most 19"),
        (b'{"a": NaN}', "NaN is not an allowed number"),
        (b'{"a": 1, "a": 2}', "the key 'a' appears twice"),
        (b"\x00\xff" * 100, "not valid JSON"),
        (b"   \n", "the map file is empty"),
    ],
)
def test_hostile_map_files_are_refused_by_name(
    tmp_path: Path, content: bytes, message: str
) -> None:
    path = tmp_path / "m.json"
    path.write_bytes(content)
    with pytest.raises(MapError) as err:
        load(path)
    assert message in str(err.value)


def test_special_files_and_oversized_maps_are_refused(tmp_path: Path, good_map_doc: dict) -> None:
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero"), tmp_path):
        with pytest.raises(MapError, match="not a regular file"):
            load(path)
        with pytest.raises(MapError, match="not a regular file"):
            load_map_isolated(path, 1 << 20, 5.0)
    big = tmp_path / "big.json"
    big.write_bytes(json.dumps(good_map_doc).encode() + b" " * 70_000)
    with pytest.raises(MapError, match="bytes; a map is at most 65536 bytes"):
        load(big, max_bytes=65536)
    with pytest.raises(MapError, match="bytes; a map is at most 65536 bytes"):
        load_map_isolated(big, 65536, 5.0)


def test_the_isolated_loader_loads_and_times_out(tmp_path: Path, good_map_doc: dict) -> None:
    path = tmp_path / "m.json"
    path.write_text(json.dumps(good_map_doc))
    got = load_map_isolated(path, 1 << 20, 30.0)
    assert got.checksum == good_map_doc["checksum"]
    with pytest.raises(MapError, match=r"loading took over 0.001 s \(map.load_timeout_s\)"):
        load_map_isolated(path, 1 << 20, 0.001)
    path.write_bytes(b"[" * 100_000)
    with pytest.raises(MapError, match="JSON nested too deeply"):
        load_map_isolated(path, 1 << 20, 30.0)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_fuzzed_maps_load_or_fail_with_a_message(good_map_doc: dict, data: st.DataObject) -> None:
    """Any field of a (re-signed) map replaced by anything: a map or a MapError."""
    doc = copy.deepcopy(good_map_doc)
    value = data.draw(config_values)
    where = data.draw(st.sampled_from(["boundary", "landmarks", "dock", "keepout_zones", "lm"]))
    if where == "lm":
        key = data.draw(st.sampled_from(["id", "xyz", "covariance", "descriptor", "keyframe"]))
        doc["landmarks"][data.draw(st.integers(0, 7))][key] = value
    else:
        doc[where] = value
    try:
        lawn = from_document(_signed(doc))
    except MapError as exc:
        assert str(exc)
        return
    assert not lawn.problems()
    assert np.all(np.abs(lawn.boundary) <= 1e4)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400))
def test_fuzzed_map_bytes_fail_with_a_message(tmp_path_factory: Any, content: bytes) -> None:
    path = tmp_path_factory.mktemp("map") / "m.json"
    path.write_bytes(content)
    with pytest.raises(MapError):
        load(path)


def _load_in_a_daemonic_child(path: str, out: Any) -> None:
    try:
        out.put(load_map_isolated(Path(path), 1 << 20, 60.0).checksum)
    except MapError as exc:
        out.put(f"MapError: {exc}")


def test_the_isolated_loader_works_in_a_daemonic_process(
    tmp_path: Path, good_map_doc: dict
) -> None:
    """The estimation process is a daemonic child of the supervisor: it may not use
    multiprocessing children, the loader must still work there."""
    import multiprocessing

    path = tmp_path / "m.json"
    path.write_text(json.dumps(good_map_doc))
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_load_in_a_daemonic_child, args=(str(path), out), daemon=True)
    proc.start()
    got = out.get(timeout=120)
    proc.join(10)
    assert got == good_map_doc["checksum"]
