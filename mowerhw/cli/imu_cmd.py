"""``mowerhw imu characterize``: the gyro's noise figures from a static recording."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mowerhw.cli.common import add_plot_argument, number, output_file, print_json, seed_number


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("imu", help="characterise the IMU's gyro noise from a static recording")
    isub = p.add_subparsers(dest="imu_command", metavar="ACTION", required=True)
    ch = isub.add_parser(
        "characterize",
        help="Allan deviation of a static recording: white noise, bias instability, random "
        "walk, and the config keys to use",
        description="Record the mower standing still for 30 min or more (`mowerhw record "
        "--config FILE --out still.mcap --duration 3600`), then run this on the MCAP (or on a "
        "CSV of t, gx, gy, gz in s and rad/s). It prints the three figures per axis and the "
        "imu keys to put in the config (the largest over the axes).",
    )
    ch.add_argument("recording", type=Path, metavar="RECORDING", help="an MCAP or a CSV")
    add_plot_argument(ch, "draw the Allan deviation (default: next to the recording)")
    ch.add_argument("--json", action="store_true", help="print one JSON object")
    ch.set_defaults(handler=_characterize)

    st = isub.add_parser(
        "simulate",
        help="write a static recording of a simulated gyro grade (to try characterize on)",
    )
    st.add_argument("--grade", required=True, choices=("vn100", "bmi088", "mpu6050"))
    st.add_argument(
        "--duration",
        type=number(float, gt=0, le=1e6),
        default=7200.0,
        help="seconds (default 7200)",
    )
    st.add_argument("--seed", type=seed_number, default=0)
    st.add_argument(
        "--out",
        type=output_file,
        required=True,
        help="FILE.csv, or FILE.mcap (VN-100 binary bytes)",
    )
    st.set_defaults(handler=_simulate)


def _load(path: Path) -> tuple:
    """Gyro times and samples of a recording: an MCAP's VN-100 bytes through the driver's
    parser and extractor (as the daemon reads them), or a CSV."""
    from mowerhw.imu.allan import CharacterizeError, load_csv

    if path.suffix.lower() != ".mcap":
        return (*load_csv(path), "CSV t, gx, gy, gz")
    if not path.exists():
        raise CharacterizeError(f"{path}: no such file")
    import base64

    import numpy as np

    from drivers.imu.vn100 import ImuExtractor, Vn100Parser
    from mowerhw.recording.mcap import RecordingError, RecordingRead

    parser, extractor = Vn100Parser(), ImuExtractor()
    t, gyro = [], []
    try:
        for topic, _, msg in RecordingRead(path).messages():
            if topic != "/vn100/raw":
                continue
            host_ns = int(msg["host_time_ns"])
            for item in parser.feed(base64.b64decode(msg["data"])):
                s = extractor.sample(item, host_ns)
                if s is None or not s.finite:
                    continue
                dev = s.device_time_ns
                t.append(dev * 1e-9 if dev is not None else s.t)
                gyro.append(s.gyro)
    except RecordingError as exc:  # e.g. the sensor's raw bytes: `mowerhw record` makes one
        raise CharacterizeError(f"{exc}; record one with `mowerhw record`") from None
    if not t:
        raise CharacterizeError(f"{path}: no VN-100 gyro samples in /vn100/raw")
    return np.asarray(t), np.asarray(gyro), "MCAP /vn100/raw through the VN-100 parser"


def _characterize(args: argparse.Namespace) -> int:
    from mowerhw.imu.allan import CharacterizeError, characterize, plot_allan

    try:
        t, gyro, source = _load(args.recording)
        result = characterize(t, gyro, source)
    except CharacterizeError as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        return 1
    report = result.as_dict()
    if args.plot is not None:
        out = args.recording.with_suffix(".allan.png") if args.plot is True else args.plot
        report["plot"] = str(plot_allan(result, out))
    if args.json:
        print_json(report)
        return 0
    print(
        f"recording    {args.recording}: {result.samples} samples, {result.duration_s / 60:.1f} "
        f"min at {result.rate_hz:.1f} Hz ({source})"
    )
    print(
        "axis   white noise (rad/s/√Hz)   bias instability (rad/s, at τ)   random walk (rad/s/√s)"
    )
    for k, axis in enumerate(("x", "y", "z")):
        rw = result.rate_random_walk[k]
        rw_text = f"{rw:.3g}" if rw == rw else "not reached"
        print(
            f"{axis:<6} {result.noise_density[k]:<25.3g} "
            f"{result.bias_instability[k]:.3g} (τ {result.bias_instability_tau_s[k]:.0f} s)"
            f"{'':<12} {rw_text}"
        )
    for note in result.notes:
        print(f"note         {note}")
    print("\nput in the config (the largest over the axes):\nimu:")
    for key, value in result.config_values().items():
        print(f"  {key}: {'null' if value is None else f'{value:.4g}'}")
    if "plot" in report:
        print(f"\nplot         {report['plot']}")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    from mowerhw.imu.allan import static_recording

    t, gyro = static_recording(args.grade, args.duration, args.seed)
    if args.out.suffix.lower() == ".mcap":
        _write_mcap(args.out, t, gyro)
    else:
        import numpy as np

        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(
            args.out,
            np.column_stack([t, gyro]),
            delimiter=",",
            header="t,gx,gy,gz",
            comments="",
            fmt="%.9g",
        )
    print(f"{args.out}: {t.size} samples of a still {args.grade} over {args.duration:.0f} s")
    return 0


def _write_mcap(path: Path, t, gyro) -> None:
    """The samples as a VN-100 would send them (binary: TimeStartup + AngularRate), in 1 s
    chunks of serial bytes, as ``mowerhw record`` writes them."""
    import struct

    import drivers.imu.vn100_binary as binary
    from mowerhw.recording.mcap import Recorder

    path.parent.mkdir(parents=True, exist_ok=True)
    rec = Recorder(path, queue_size=1 << 16)
    chunk = bytearray()
    last_ns = 0
    for k in range(t.size):
        ns = round(t[k] * 1e9)
        chunk += binary.encode_packet(
            {
                "Common.TimeStartup": struct.pack("<Q", ns + 1_000_000_000),
                "Common.AngularRate": struct.pack("<3f", *gyro[k]),
            }
        )
        if k % 100 == 99 or k == t.size - 1:
            rec.serial(ns + 5_000_000, bytes(chunk))
            chunk.clear()
            last_ns = ns
    rec.close(timeout=120.0)
    if rec.error or rec.dropped:
        raise OSError(f"recording {path}: {rec.error or f'{rec.dropped} messages dropped'}")
    del last_ns
