#!/usr/bin/env python3
"""Benchmark: VN-100 parser throughput on the real VN-100 Rugged captures and on binary output.

Feeds each stream to :class:`drivers.imu.vn100.Vn100Parser` in chunks the size a serial read
returns (64 B and 4 KiB), best of ``--repeat`` runs, and prints one JSON object: MB/s,
packets/s, µs per packet, and the headroom over the fastest serial link (921600 baud ≈
92 kB/s) — how many times faster than the wire the parser is. The binary stream is what the
driver configures (TimeStartup + YawPitchRoll + AngularRate + Accel + MagPres, 70 bytes a packet),
with 1 % of the packets damaged so the resynchronisation path is part of the measurement.

Run: ``.venv/bin/python tools/bench_vn100_parser.py`` (``--repeat 5``).
"""

from __future__ import annotations

import argparse
import json
import random
import time
from dataclasses import asdict
from pathlib import Path

from drivers.imu.vn100 import COMMON_FIELDS, Vn100Parser
from drivers.imu.vn100_binary import FIELDS, encode_packet, pack_values

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "vn100"
WIRE_BYTES_PER_S = 921600 / 10  # 8N1: 10 bits per byte
BINARY_PACKETS = 20000


def binary_stream(n_packets: int, damaged: float = 0.01, seed: int = 0) -> bytes:
    """``n_packets`` 100 Hz common-group packets with the fields the driver asks for
    (``COMMON_FIELDS``), encoded by the sensor side's :func:`encode_packet`."""
    rng = random.Random(seed)
    names = [f"Common.{FIELDS[(0, bit)].name}" for bit in range(16) if COMMON_FIELDS >> bit & 1]
    out = bytearray()
    for k in range(n_packets):
        values = {
            "Common.TimeStartup": [1_000_000_000 + k * 10_000_000],
            "Common.YawPitchRoll": [10.0 + 0.01 * k, 0.5, -1.5],
            "Common.AngularRate": [0.01, -0.02, 0.3],
            "Common.Accel": [0.1, 0.0, -9.81],
            "Common.MagPres": [0.2, 0.0, 0.4, 25.0, 101.3],
        }
        pkt = bytearray(encode_packet({n: pack_values(n, values[n]) for n in names}))
        if rng.random() < damaged:
            pkt[rng.randrange(1, len(pkt))] ^= 1 << rng.randrange(8)
        out += pkt
    return bytes(out)


def run(stream: bytes, chunk: int, repeat: int) -> dict[str, float]:
    best, stats = float("inf"), None
    for _ in range(repeat):
        parser = Vn100Parser()
        t0 = time.perf_counter()
        for i in range(0, len(stream), chunk):
            parser.feed(stream[i : i + chunk])
        parser.close()
        dt = time.perf_counter() - t0
        if dt < best:
            best, stats = dt, parser.stats
    mb_s = len(stream) / best / 1e6
    return {
        "chunk_bytes": chunk,
        "mb_per_s": round(mb_s, 2),
        "packets_per_s": round(stats.packets_ok / best),
        "us_per_packet": round(best / max(stats.packets_ok, 1) * 1e6, 2),
        "headroom_over_921600_baud": round(len(stream) / best / WIRE_BYTES_PER_S, 1),
        "counts": _str_keys({k: v for k, v in asdict(stats).items() if v})
        | {"rejected": _str_keys(stats.rejected)},
    }


def _str_keys(value: object) -> object:
    """JSON objects take string keys only (the stats count some by (group, field) tuples)."""
    if isinstance(value, dict):
        return {str(k): _str_keys(v) for k, v in value.items()}
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    streams = {
        "capture_a_ascii": (DATA / "vn100-rugged-capture-a.txt").read_bytes(),
        "capture_b_ascii": (DATA / "vn100-rugged-capture-b.txt").read_bytes(),
        "binary_100hz_common_group": binary_stream(BINARY_PACKETS),
    }
    out: dict[str, object] = {}
    for name, data in streams.items():
        out[name] = {
            "bytes": len(data),
            "results": [run(data, chunk, args.repeat) for chunk in (64, 4096)],
        }
    print(json.dumps(out, indent=2))
    binary_ok = out["binary_100hz_common_group"]["results"][0]["counts"]  # type: ignore[index]
    if binary_ok.get("binary_ok", 0) < 0.95 * BINARY_PACKETS:
        raise SystemExit(f"the binary stream did not parse as the driver's packets: {binary_ok}")


if __name__ == "__main__":
    main()
