#!/usr/bin/env python3
"""Check: the VN-100 parser on a real binary log against its authors' own decoding.

``../shared/data/real/vn100-binary-waves-in-ice``: a VN-100 writing IMU-group (UncompMag,
UncompAccel, UncompGyro, Temp, Pres) and Attitude-group (YawPitchRoll, DCM, MagNed,
AccelNed) packets at 10 Hz onto an SD card, between NMEA lines and a logger's own text. The
log is fed in random chunks through :class:`drivers.imu.vn100.Vn100Parser` and
:class:`drivers.imu.vn100.ImuExtractor`; every decoded value is compared with the authors' CSV
(``parsed_by_upstream/*_B``, printed with 7 significant digits, so a value agrees to half a
unit of its last printed digit: 5e-7 relative).

Then the compass (issue 18): each sample's magnetic field (T, from ``Imu.UncompMag``) and
specific force, turned from the VN-100's frame (x forward, y right, z down) into mowerhw's
body frame (z up) and levelled (:func:`mowerhw.common.magnetic.field_in_body`), against the
sensor's own yaw (``Attitude.YawPitchRoll``, from its compensated field): the difference is
one constant (the field's uncompensated offset) plus the spread reported — with the
levelling, and without it (the logger sat tilted ~14° and ~7° on the ice).

Prints one JSON object per log. Run: ``.venv/bin/python tools/check_real_vn100.py``.
"""

from __future__ import annotations

import json
import random
import sys
from pathlib import Path

import numpy as np

from drivers.imu.vn100 import ImuExtractor, Vn100Parser
from mowerhw.common.geometry import wrap_angle
from mowerhw.common.magnetic import field_in_body

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
LOGS = DATA / "vn100-binary-waves-in-ice"
#: the CSV's columns, each as (field, element, factor from our SI value to the CSV's unit)
COLUMNS: list[tuple[str, str, int, float]] = [
    *[(f"Mag{a}", "Imu.UncompMag", i, 1e4) for i, a in enumerate("XYZ")],
    *[(f"Acc{a}", "Imu.UncompAccel", i, 1.0) for i, a in enumerate("XYZ")],
    *[(f"Gyro{a}", "Imu.UncompGyro", i, 1.0) for i, a in enumerate("XYZ")],
    ("Temp", "Imu.Temp", 0, 1.0),
    ("Pres", "Imu.Pres", 0, 1e-3),
    *[
        (a, "Attitude.YawPitchRoll", i, 180.0 / np.pi)
        for i, a in enumerate(["Yaw", "Pitch", "Roll"])
    ],
    *[(f"DCM{i + 1}", "Attitude.DCM", i, 1.0) for i in range(9)],
    *[(f"MagNED{i + 1}", "Attitude.MagNed", i, 1e4) for i in range(3)],
    *[(f"AccNED{i + 1}", "Attitude.AccelNed", i, 1.0) for i in range(3)],
]


def read_upstream_csv(path: Path) -> np.ndarray:
    """The authors' rows (29 values each; their file also holds one stray one-value row)."""
    rows = []
    for line in path.read_text().splitlines()[1:]:
        values = [v for v in line.replace(" ", "").split(",") if v]
        if len(values) == len(COLUMNS):
            rows.append([float(v) for v in values])
    return np.array(rows)


def decode(raw: bytes, seed: int = 0) -> tuple[Vn100Parser, ImuExtractor, np.ndarray]:
    """The log in random chunks (1–700 B, as serial reads come) → parser → IMU samples;
    returns the parser, the extractor and the decoded values in the CSV's columns."""
    rng = random.Random(seed)
    parser, extractor = Vn100Parser(), ImuExtractor()
    items = []
    pos = 0
    while pos < len(raw):
        step = rng.randint(1, 700)
        items += parser.feed(raw[pos : pos + step])
        pos += step
    parser.close()
    rows = []
    for k, item in enumerate(items):
        extractor.sample(item, k)
        if hasattr(item, "offsets"):
            rows.append([np.atleast_1d(item[f])[i] * s for _, f, i, s in COLUMNS])
    return parser, extractor, np.array(rows)


def align(ours: np.ndarray, ref: np.ndarray, rel_tol: float = 1e-6) -> tuple[list, list[int]]:
    """Our packets paired, in order, with the authors' rows that hold the same values (to
    their print precision); the indices of our packets their CSV does not have."""
    pairs, unmatched = [], []
    j = 0
    for k, row in enumerate(ours):
        if j < len(ref):
            rel = np.abs(row - ref[j]) / np.maximum(np.abs(ref[j]), 1e-6)
            if rel.max() <= rel_tol:
                pairs.append((k, j))
                j += 1
                continue
        unmatched.append(k)
    return pairs, unmatched


def compare(name: str, seed: int = 0) -> dict[str, object]:
    parser, extractor, ours = decode((LOGS / "raw" / name).read_bytes(), seed)
    ref = read_upstream_csv(LOGS / "parsed_by_upstream" / f"{name}_B")
    out: dict[str, object] = {
        "log": name,
        "packets_accepted": parser.stats.binary_ok,
        "crc_rejected": parser.stats.bad_crc,
        "imu_samples": extractor.stats.samples,
        "other_ascii_lines": parser.stats.other_ascii,
        "garbage_bytes": parser.stats.garbage_bytes,
        "malformed": parser.stats.malformed,
        "upstream_rows": int(ref.shape[0]),
    }
    pairs, unmatched = align(ours, ref)
    out["packets_not_in_upstream_csv"] = unmatched
    out["upstream_rows_matched"] = len(pairs)
    if len(pairs) != ref.shape[0]:
        out["error"] = f"only {len(pairs)} of the authors' {ref.shape[0]} rows found in order"
    ours = ours[[k for k, _ in pairs]]
    ref = ref[[j for _, j in pairs]]
    diff = np.abs(ours - ref)
    rel = diff / np.maximum(np.abs(ref), 1e-30)
    out["values_compared"] = int(diff.size)
    out["max_abs_diff"] = {
        c[0]: float(f"{d:.3g}") for c, d in zip(COLUMNS, diff.max(0), strict=True)
    }
    out["max_rel_diff"] = float(f"{rel.max():.3g}")
    return out


#: the VN-100's body frame (x forward, y right, z down) → mowerhw's (x forward, y left, z up)
VN_TO_BODY = np.diag([1.0, -1.0, -1.0])


def compass(name: str) -> dict[str, object]:
    """The levelled field direction α against the sensor's own yaw (module doc): α − yaw
    (the VN-100's yaw turns clockwise, α counter-clockwise: the same angle for a still
    field), its median and the spread about it (p50 / p95 of |deviation|, degrees)."""
    items = Vn100Parser().feed((LOGS / "raw" / name).read_bytes())
    extractor = ImuExtractor()
    out: dict[str, object] = {"log": name}
    for label, use_accel in (("levelled", True), ("not_levelled", False)):
        diffs = []
        for k, item in enumerate(items):
            sample = extractor.sample(item, k)
            if sample is None or sample.mag is None or sample.accel is None:
                continue
            accel = VN_TO_BODY @ sample.accel if use_accel else None
            reading = field_in_body(VN_TO_BODY @ sample.mag, accel)
            if reading is None:
                continue
            yaw = float(np.atleast_1d(item["Attitude.YawPitchRoll"])[0])
            diffs.append(wrap_angle(reading.alpha - yaw))
        d = np.degrees(np.array(diffs))
        mid = float(np.median(d))
        dev = np.degrees(np.abs(wrap_angle(np.radians(d - mid))))
        out[label] = {
            "samples": int(d.size),
            "offset_deg": round(mid, 2),
            "spread_deg_p50": round(float(np.percentile(dev, 50)), 2),
            "spread_deg_p95": round(float(np.percentile(dev, 95)), 2),
        }
    return out


def main() -> None:
    if not LOGS.exists():
        sys.exit(f"no real data at {LOGS}")
    for name in ("F00294", "F00379"):
        print(json.dumps(compare(name)))
        print(json.dumps(compass(name)))


if __name__ == "__main__":
    main()
