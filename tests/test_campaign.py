"""Evaluation campaigns (`mowerhw eval`): local processes and a Dask cluster give one table;
IMU noise from data (`mowerhw imu characterize`)."""

import csv
import json

import numpy as np
import pytest

from mowerhw.cli import main
from mowerhw.evaluation.campaign import RunSpec, run_campaign, seeds_of, summarise, write_table

WALL = ("teach_wall_s", "mow_wall_s")


def _table(rows):
    return [{k: v for k, v in r.items() if k not in WALL} for r in rows]


def test_seed_lists():
    assert seeds_of("1-3,7") == [1, 2, 3, 7] and seeds_of("5") == [5]


@pytest.mark.slow
@pytest.mark.slow
def test_local_workers_and_a_dask_cluster_give_the_same_table(tmp_path):
    distributed = pytest.importorskip("distributed", reason="dask[distributed] not installed")
    specs = [RunSpec(s, seed, "bearing", 15.0) for s in ("paper", "U-sparse") for seed in (1, 2)]
    local = run_campaign(specs, workers=2, progress=False)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = run_campaign(specs, scheduler=client, progress=False)
    assert _table(local) == _table(remote)
    assert [r["scenario"] for r in local] == ["paper", "paper", "U-sparse", "U-sparse"]
    assert all(r["error"] is None and r["teach_ok"] for r in local), local
    path = write_table(local, tmp_path / "results.csv")
    with path.open() as fh:
        assert len(list(csv.DictReader(fh))) == 4
    summary = {s["scenario"]: s for s in summarise(local)}
    assert summary["paper"]["runs"] == 2 and summary["paper"]["missed_halts"] == 0


def test_eval_command_refuses_unknown_scenarios_and_rough_ground_at_pixel_level(capsys):
    assert main(["eval", "--scenarios", "moon"]) == 2
    assert "unknown scenario moon" in capsys.readouterr().err
    assert main(["eval", "--scenarios", "strip-bumps", "--level", "pixel"]) == 2
    assert "flat ground only" in capsys.readouterr().err


def test_eval_command_writes_the_table_and_summary(tmp_path, capsys):
    out = tmp_path / "ev"
    code = main(
        ["eval", "--scenarios", "paper", "--seeds", "1", "--mow-s", "5", "--workers", "1"]
        + ["--out", str(out), "--json"]
    )
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["runs"] == 1 and (out / "results.csv").exists()
    assert report["summary"][0]["scenario"] == "paper"


@pytest.mark.parametrize("grade", ["vn100", "bmi088", "mpu6050"])
def test_characterize_recovers_the_simulated_white_noise(grade, tmp_path, capsys):
    from mowerhw.imu.grades import IMU_GRADES

    path = tmp_path / f"{grade}.csv"
    assert main(["imu", "simulate", "--grade", grade, "--duration", "600", "--out", str(path)]) == 0
    capsys.readouterr()
    assert main(["imu", "characterize", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    n = report["config"]["imu"]["gyro_noise_density"]
    assert n == pytest.approx(IMU_GRADES[grade].noise_density, rel=0.05)


def test_characterize_reads_a_vn100_mcap_through_the_parser(tmp_path, capsys):
    path = tmp_path / "still.mcap"
    args = ["imu", "simulate", "--grade", "bmi088", "--duration", "120", "--out", str(path)]
    assert main(args) == 0
    capsys.readouterr()
    assert main(["imu", "characterize", str(path), "--json", "--plot"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["samples"] == 12000 and report["rate_hz"] == pytest.approx(100.0)
    assert report["source"].startswith("MCAP")
    assert (tmp_path / "still.allan.png").exists()


def test_characterize_refuses_what_it_cannot_use(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,gx,gy,gz\n0,1,2\n")
    assert main(["imu", "characterize", str(bad)]) == 1
    assert "expected columns t, gx, gy, gz" in capsys.readouterr().err
    short = tmp_path / "short.csv"
    np.savetxt(short, np.column_stack([np.arange(50) * 0.01, np.zeros((50, 3))]), delimiter=",")
    assert main(["imu", "characterize", str(short)]) == 1
    assert "at least 1000" in capsys.readouterr().err
    # the sensor's raw bytes named .mcap: refused as what they are, not an internal error
    raw = tmp_path / "raw.mcap"
    raw.write_bytes(b"\xfa\x14\x3e\x00\x3a\x00" + bytes(range(256)) * 4)
    assert main(["imu", "characterize", str(raw)]) == 1
    assert "not an MCAP recording" in capsys.readouterr().err


def test_a_yards_mower_is_configured_with_its_own_sensors():
    """The evaluation's localizer is configured as that yard's user would configure theirs:
    the IMU's grade, the camera's stamp jitter where it has one (none: nothing set), and a
    bearing σ widened with a camera noisier than the default's 3 px (U-sparse's 5 px)."""
    from mowerhw.config import MowConfig
    from mowerhw.evaluation.campaign import scenario_config
    from mowerhw.sim.scenarios import SCENARIOS

    default = MowConfig().bearing_sigma_rad
    for name, scenario in SCENARIOS.items():
        cfg = scenario_config(name)
        assert cfg.imu.grade == scenario.sensors.imu.name
        assert cfg.mow.frame_stamp_sigma_s == scenario.sensors.camera.stamp_jitter_s
        px = max(3.0, scenario.sensors.camera.pixel_sigma)
        assert cfg.mow.bearing_sigma_rad == pytest.approx(default * px / 3.0)
    assert scenario_config("trees-dense").mow.frame_stamp_sigma_s == 0.003
    assert scenario_config("paper").mow.frame_stamp_sigma_s == 0.0
    assert scenario_config("paper").mow.bearing_sigma_rad == default
    assert scenario_config("U-sparse").mow.bearing_sigma_rad == pytest.approx(default * 5 / 3)


def test_matched_noise_is_the_simulated_sensors_own():
    """For a NEES that tests the filter (its models the truth's): the ground speed's white
    noise and quantum as a density at its rate, sideways slip at the floor, the gyro scale
    prior at its grade's (the simulated VN-100's only its change between runs, 0.1 %, not the
    shipped 0.5 % floor; with a taught scale that change alone), the gyro's white noise and
    rate random walk at its grade's (the simulated gyro's, without the shipped 1.64 margin);
    what a white density cannot stand for is listed; the teach section stays as shipped."""
    import math

    from mowerhw.evaluation.campaign import MATCHED_LATERAL_NOISE, matched_noise, scenario_config
    from mowerhw.imu.grades import IMU_GRADES

    shipped = scenario_config("paper")
    cfg, unmatched = matched_noise(shipped, "paper")
    assert cfg.mow.speed_noise == pytest.approx(math.sqrt(0.005**2 + 0.001**2 / 12) / math.sqrt(10))
    assert cfg.mow.lateral_noise == MATCHED_LATERAL_NOISE < shipped.mow.lateral_noise
    assert cfg.mow.gyro_scale_sigma == 0.001 < shipped.mow.gyro_scale_sigma
    assert cfg.mow.gyro_scale_sigma_taught == 0.001
    vn100 = IMU_GRADES["vn100"]
    assert cfg.mow.gyro()[:2] == (vn100.noise_density, vn100.rate_random_walk)
    assert shipped.mow.gyro()[0] == pytest.approx(1.64 * vn100.noise_density)
    assert unmatched == []
    assert cfg.teach == shipped.teach and cfg.mow.bearing_sigma_rad == shipped.mow.bearing_sigma_rad
    slip, unmatched = matched_noise(scenario_config("slope-slip"), "slope-slip")
    assert slip.mow.gyro_scale_sigma == pytest.approx(math.hypot(0.03, 0.003))  # ±3 %, and drift
    assert slip.mow.gyro_scale_sigma_taught == 0.003  # its MPU-6050's change between runs
    mpu = IMU_GRADES["mpu6050"]
    assert slip.mow.gyro()[0] == mpu.noise_density
    assert len(unmatched) == 4 and any("slip" in u for u in unmatched)
    assert any("bias instability" in u for u in unmatched)  # flicker, not a random walk
