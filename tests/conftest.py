"""Shared test settings: hypothesis profiles (CI runs the 'ci' profile, deterministic)."""

import importlib.util
import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    max_examples=200,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", max_examples=100, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture
def map_file(tmp_path):
    """A small valid lawn map file (an ellipse, six landmarks), for the map tools' tests."""
    import numpy as np

    from mowerhw.map import Landmark, LawnMap

    a = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    m = LawnMap(
        boundary=np.column_stack([6 * np.cos(a), 4 * np.sin(a)]),
        landmarks=[
            Landmark(i, np.array([8.0 * np.cos(i), 8.0 * np.sin(i), 1.0]), np.eye(3) * 1e-4)
            for i in range(6)
        ],
    )
    path = tmp_path / "lawn.json"
    m.save(path)
    return path


# ------------------------------------------------------------- the bench (daemon + mock hardware)


def _multicast_works() -> str:
    """'' if two python-can udp_multicast buses on this host hear each other, else why not
    (``MOWERHW_NO_MULTICAST=1`` says not: how a CI without multicast is tried here)."""
    if os.environ.get("MOWERHW_NO_MULTICAST"):
        return "MOWERHW_NO_MULTICAST is set"
    import can

    from mowerhw.bench.hil import _free_udp_port

    port = _free_udp_port()
    try:
        a = can.Bus(interface="udp_multicast", channel="239.74.163.9", port=port)
        b = can.Bus(interface="udp_multicast", channel="239.74.163.9", port=port)
    except Exception as exc:
        return f"cannot open a udp_multicast bus: {exc}"
    try:
        a.send(can.Message(arbitration_id=0x18FEF100, data=b"\x01", is_extended_id=True))
        got = b.recv(1.0)
        return "" if got is not None else "multicast frames do not arrive on the loopback"
    finally:
        a.shutdown()
        b.shutdown()


@pytest.fixture(scope="session")
def multicast():
    why = _multicast_works()
    if why:
        pytest.skip(f"the bench's CAN between processes needs IP multicast: {why}")


@pytest.fixture(scope="session")
def yard_map(tmp_path_factory, multicast):
    """The bench yard's map, from a pixel-level simulated teach (seed 7), once per session."""
    from mowerhw.evaluation.pixel import run_teach_pixel
    from mowerhw.map import LawnMap

    out = run_teach_pixel("paper", 7)
    assert out.result is not None, out.error
    path = tmp_path_factory.mktemp("map") / "lawn.json"
    LawnMap.from_teach_result(out.result).save(path)
    return path


#: the files whose tests run the daemon in real time against the bench's mock hardware
REALTIME_BENCH_FILES = ("test_daemon_bench.py", "test_web_page.py")


def _is_realtime_bench(nodeid: str) -> bool:
    return nodeid.split("::", 1)[0].rsplit("/", 1)[-1] in REALTIME_BENCH_FILES


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The real-time bench tests first: under two workers the longest share starts at once."""
    items.sort(key=lambda item: not _is_realtime_bench(item.nodeid))  # stable


if importlib.util.find_spec("xdist") is not None:
    from xdist.scheduler import LoadScopeScheduling

    class _ByFileScheduling(LoadScopeScheduling):
        """pytest-xdist's workers (`./dev test` runs two) get whole test files, so a file's
        module fixtures are made once; the real-time bench files share one worker, one after
        another, so the yard's map is taught once and two real-time daemons never compete for
        the machine's cores."""

        def _split_scope(self, nodeid: str) -> str:
            return "realtime-bench" if _is_realtime_bench(nodeid) else nodeid.split("::", 1)[0]

    def pytest_xdist_make_scheduler(
        config: pytest.Config, log: object
    ) -> LoadScopeScheduling | None:
        """``-n N`` (pytest-xdist's ``--dist load``) schedules by file as above."""
        return _ByFileScheduling(config, log) if config.getvalue("dist") == "load" else None
