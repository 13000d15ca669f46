"""VN-100 wire protocol: real captures, checks, binary packets, resynchronisation, fuzzing."""

import struct
from pathlib import Path

import numpy as np
import pytest
from _tools import load_tool
from hypothesis import given, settings
from hypothesis import strategies as st

import drivers.imu.vn100_binary as binary
from drivers.imu.mock import MockVn100, still_source
from drivers.imu.vn100 import (
    BinaryPacket,
    ErrorReply,
    ImuExtractor,
    QmrMessage,
    RegisterReply,
    Vn100Parser,
    YmrMessage,
    YprAccelRateMessage,
    ascii_command,
    crc16,
    imu_sample_from,
    xor8,
)

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "vn100"
CAPTURE_A = DATA / "vn100-rugged-capture-a.txt"
CAPTURE_B = DATA / "vn100-rugged-capture-b.txt"
needs_data = pytest.mark.skipif(not CAPTURE_A.exists(), reason="shared/data not present")


YMR_A = (
    b"VNYMR,+010.000,-001.000,+002.000,+00.1000,+00.2000,+00.3000,-00.100,+00.200,-09.810,"
    b"+00.010000,-00.020000,+00.030000"
)
YMR_B = (
    b"VNYMR,+030.000,+000.000,+000.000,+00.2000,+00.0500,+00.4500,+00.000,+00.000,-09.810,"
    b"+00.001000,-00.002000,+00.001500"
)


def binary_packet(groups: int, masks: list[int], payload: bytes) -> bytes:
    body = bytes([groups]) + struct.pack(f"<{len(masks)}H", *masks) + payload
    return b"\xfa" + body + struct.pack(">H", crc16(body))


def test_check_algorithms():
    assert crc16(b"123456789") == 0x31C3  # XMODEM check value (docs/design.md §7)
    assert xor8(b"VNRRG,05") == int(ascii_command("VNRRG,05")[10:12], 16)
    assert ascii_command("VNRRG,05", crc=True).endswith(f"*{crc16(b'VNRRG,05'):04X}\r\n".encode())


@needs_data
def test_capture_a_every_line_parses():
    p = Vn100Parser()
    items = p.feed(CAPTURE_A.read_bytes())
    p.close()
    assert len(items) == 975 and all(isinstance(i, YmrMessage) for i in items)
    assert p.stats.packets_ok == 975 and p.stats.rejected == 0 and p.stats.garbage_bytes == 0
    first = items[0]  # $VNYMR,+170.786,-005.153,+009.880,-00.1957,…,-01.272982*68
    assert (first.yaw, first.pitch, first.roll) == (170.786, -5.153, 9.880)
    assert np.allclose(first.mag, [-0.1957, 0.2218, 0.6401])
    assert np.allclose(first.accel, [-0.952, -2.181, -9.775])
    assert np.allclose(first.gyro, [-0.074567, 0.621957, -1.272982])


@needs_data
def test_capture_b_cut_first_and_last_lines_are_rejected_and_counted():
    data = CAPTURE_B.read_bytes()
    first_line = data.split(b"\n", 1)[0] + b"\n"
    p = Vn100Parser()
    items = []
    for k in range(0, len(data), 777):  # arbitrary chunking, as a serial port delivers
        items += p.feed(data[k : k + 777])
    p.close()
    complete = data.count(b"$") - 1  # every line but the cut last one
    assert len(items) == complete == p.stats.packets_ok
    assert p.stats.garbage_bytes == len(first_line)  # the cut first line: skipped bytes …
    assert p.stats.headless_line == 1  # … counted as one line whose start was lost
    assert p.stats.truncated == 1  # the cut last line
    assert p.stats.rejected == 2
    assert p.stats.bad_checksum == p.stats.malformed == 0


def test_a_line_rejected_by_its_check_is_counted_once():
    line = b"$VNYMR,+1.0*00\r\n"  # wrong checksum
    p = Vn100Parser()
    for chunk in (line[:5], line[5:12], line[12:] + line):
        p.feed(chunk)
    assert p.stats.bad_checksum == 2 and p.stats.headless_line == 0 and p.stats.rejected == 2
    p = Vn100Parser()
    p.feed(b"MR,+1.0*4F\r\nPR,+1*3A\n")  # two line ends without their start
    assert p.stats.headless_line == 2 and p.stats.packets_ok == 0


def test_crlf_and_lf_and_crc16_lines():
    body = YMR_A
    crlf = b"$" + body + b"*%02X\r\n" % xor8(body)
    lf = b"$" + body + b"*%02X\n" % xor8(body)
    crc = b"$" + body + b"*%04X\r\n" % crc16(body)
    p = Vn100Parser()
    out = p.feed(crlf + lf + crc)
    assert len(out) == 3 and all(isinstance(m, YmrMessage) for m in out)
    assert out[2].gyro.tolist() == [0.01, -0.02, 0.03]


def test_other_ascii_messages_and_replies():
    msgs = [
        "VNQMR,+0.000,+0.000,+0.383,+0.924,+0.2,+0.0,+0.4,+0.0,+0.0,-9.8,+0.1,+0.0,+0.0",
        "VNYBA,+1.0,+2.0,+3.0,+0.1,+0.2,+0.3,+0.01,+0.02,+0.03",
        "VNYIA,+1.0,+2.0,+3.0,+0.1,+0.2,+0.3,+0.01,+0.02,+0.03",
        "VNRRG,05,921600",
        "VNERR,07",
    ]
    data = b"".join(b"$" + m.encode() + b"*%02X\r\n" % xor8(m.encode()) for m in msgs)
    out = Vn100Parser().feed(data)
    assert isinstance(out[0], QmrMessage) and np.allclose(
        out[0].quaternion_wxyz, [0.924, 0, 0, 0.383]
    )
    assert isinstance(out[1], YprAccelRateMessage) and out[1].header == "VNYBA"
    assert out[2].header == "VNYIA"
    assert out[3] == RegisterReply("VNRRG", 5, ("921600",))
    assert isinstance(out[4], ErrorReply) and out[4].meaning == "invalid parameter"


def test_binary_common_group_fields_in_si():
    payload = (
        struct.pack("<Q", 123_456_789_000)
        + struct.pack("<3f", 90.0, -10.0, 5.0)
        + struct.pack("<4f", 0.0, 0.0, 0.70710678, 0.70710678)
        + struct.pack("<3f", 0.1, -0.2, 0.3)
        + struct.pack("<3f", 0.0, 0.0, -9.81)
        + struct.pack("<6f", 0.1, 0.2, -9.7, 0.01, 0.02, 0.03)
        + struct.pack("<5f", 0.2, 0.1, 0.4, 21.5, 101.3)
    )
    mask = (1 << 0) | (1 << 3) | (1 << 4) | (1 << 5) | (1 << 8) | (1 << 9) | (1 << 10)
    (pkt,) = Vn100Parser().feed(binary_packet(0x01, [mask], payload))
    assert isinstance(pkt, BinaryPacket)
    assert pkt["Common.TimeStartup"] == 123_456_789_000
    assert np.allclose(pkt["Common.YawPitchRoll"], np.radians([90.0, -10.0, 5.0]))
    assert np.allclose(pkt["Common.AngularRate"], [0.1, -0.2, 0.3], atol=1e-7)
    assert np.allclose(pkt["Common.Accel"], [0, 0, -9.81], atol=1e-6)
    assert np.allclose(pkt["Common.Imu"], [0.1, 0.2, -9.7, 0.01, 0.02, 0.03], atol=1e-6)
    assert np.allclose(pkt["Common.MagPres"], [0.2e-4, 0.1e-4, 0.4e-4, 21.5, 101300.0], rtol=1e-6)
    assert np.allclose(pkt["Common.Quaternion"], [0, 0, 0.70710678, 0.70710678])


def test_binary_with_several_groups():
    # common: TimeStartup; IMU group: Temp, Pres, AngularRate; attitude: YawPitchRoll
    payload = (
        struct.pack("<Q", 5)
        + struct.pack("<ff", 30.0, 100.0)
        + struct.pack("<3f", 1.0, 2.0, 3.0)
        + struct.pack("<3f", 10.0, 0.0, 0.0)
    )
    pkt_bytes = binary_packet(
        0x01 | 0x04 | 0x10, [1, (1 << 4) | (1 << 5) | (1 << 10), 1 << 1], payload
    )
    (pkt,) = Vn100Parser().feed(pkt_bytes)
    assert pkt["Common.TimeStartup"] == 5
    assert pkt["Imu.Temp"] == pytest.approx(30.0) and pkt["Imu.Pres"] == pytest.approx(100000.0)
    assert np.allclose(pkt["Imu.AngularRate"], [1, 2, 3])
    assert np.allclose(pkt["Attitude.YawPitchRoll"], np.radians([10, 0, 0]))


def test_resynchronisation_after_garbage_and_false_syncs():
    body = b"VNRRG,05,115200"
    good = b"$" + body + b"*%02X\r\n" % xor8(body)
    bin_good = binary_packet(0x01, [1 << 5], struct.pack("<3f", 0.1, 0.2, 0.3))
    stream = (
        b"\x00\x13garbage"
        + b"$VNXXX,junk"
        + b"\xfa\x01\x20\x00junk"
        + good
        + b"$VN"
        + bin_good
        + good[:-5]
        + b"Z"
        + good[-4:]
        + good
    )
    p = Vn100Parser()
    out = []
    for b in stream:  # one byte at a time
        out += p.feed(bytes([b]))
    kinds = [type(o).__name__ for o in out]
    assert kinds == ["RegisterReply", "BinaryPacket", "RegisterReply"]
    assert p.stats.rejected >= 3 and p.stats.garbage_bytes > 0


def _same(a, b):
    return type(a) is type(b) and all(
        np.array_equal(np.asarray(x), np.asarray(y))
        for x, y in zip(
            vars(a).values() if not isinstance(a, BinaryPacket) else [a.payload],
            vars(b).values() if not isinstance(b, BinaryPacket) else [b.payload],
            strict=True,
        )
    )


def _sent_packets():
    s = still_source(0.0)
    mock = MockVn100("unused-link")  # not started: no port, only its packets
    ascii_pkt = mock._ascii_packet(s)
    mock.registers[75] = ["1", "8", "01", "0129"]
    bin_pkt = mock._binary_packet(1.5, s)
    return ascii_pkt, bin_pkt


@pytest.mark.parametrize("which", [0, 1], ids=["ascii-xor8", "binary-crc16"])
def test_every_single_bit_flip_is_rejected(which):
    pkt = _sent_packets()[which]
    for k in range(1, len(pkt)):
        for bit in range(8):
            bad = bytearray(pkt)
            bad[k] ^= 1 << bit
            out = Vn100Parser().feed(bytes(bad) + pkt)
            # the intact copy always; the damaged one only if its content was untouched (a
            # hex digit of the check changing case, 'A' → 'a', still checks out)
            good = Vn100Parser().feed(pkt)[0]
            assert 1 <= len(out) <= 2 and all(_same(o, good) for o in out)


def test_xor8_blind_spot_is_narrowed_by_field_validation():
    """XOR-8 cannot see the same bit flipped twice; the field rules catch most of those."""
    body = YMR_B
    bad = bytearray(body)
    bad[3] ^= 0x10  # 'Y' → 'I'
    bad[6] ^= 0x10  # '+' → ';'
    assert xor8(bytes(bad)) == xor8(body)  # the checksum still matches
    p = Vn100Parser()
    assert p.feed(b"$" + bytes(bad) + b"*%02X\r\n" % xor8(bytes(bad))) == []
    assert p.stats.malformed == 1


@settings(max_examples=300)
@given(st.binary(max_size=600), st.integers(1, 64))
def test_fuzz_arbitrary_bytes_never_raise(data, chunk):
    p = Vn100Parser()
    for k in range(0, len(data), chunk):
        p.feed(data[k : k + chunk])
    p.close()
    assert p.stats.bytes_in == len(data)


@settings(max_examples=200)
@given(st.lists(st.tuples(st.integers(0, 2), st.binary(max_size=12)), min_size=1, max_size=8))
def test_fuzz_damaged_binary_stream_accepts_only_what_was_sent(edits):
    """Inserted, flipped and dropped bytes: a CRC-16 packet accepted is one really sent."""
    _, sent = _sent_packets()
    good = Vn100Parser().feed(sent)[0]
    stream = bytearray(sent * 6)
    for op, junk in edits:
        k = len(junk) % max(len(stream), 1)
        if op == 0:
            stream[k:k] = junk
        elif op == 1 and stream:
            stream[k] ^= 0x10
        elif op == 2 and stream:
            del stream[k]
    p = Vn100Parser()
    out = p.feed(bytes(stream))
    p.close()
    assert all(_same(item, good) for item in out)
    assert p.stats.binary_ok == len(out)


@settings(max_examples=200)
@given(st.integers(0, 10**6), st.binary(min_size=1, max_size=4))
def test_fuzz_ascii_damage_never_yields_malformed_samples(pos, junk):
    """ASCII (XOR-8): whatever is accepted parses into finite, well-formed values."""
    sent, _ = _sent_packets()
    stream = bytearray(sent * 4)
    k = pos % len(stream)
    stream[k : k + len(junk)] = junk
    for item in Vn100Parser().feed(bytes(stream)):
        if isinstance(item, YmrMessage):
            assert np.all(np.isfinite(item.gyro)) and np.all(np.isfinite(item.accel))


def test_imu_samples_from_packets():
    body = YMR_A
    (ymr,) = Vn100Parser().feed(b"$" + body + b"*%02X\n" % xor8(body))
    s = imu_sample_from(ymr, 2_000_000_000, None)
    assert s.t == 2.0 and s.gyro.tolist() == [0.01, -0.02, 0.03]
    (pkt,) = Vn100Parser().feed(
        binary_packet(1, [(1 << 0) | (1 << 5)], struct.pack("<Q3f", 10**9, 0.1, 0.2, 0.3))
    )
    s = imu_sample_from(pkt, 3_000_000_000, None)
    assert s.device_time_ns == 10**9 and np.allclose(s.gyro, [0.1, 0.2, 0.3])


# ------------------------------------------------------------ the whole binary protocol


real_vn100 = load_tool("check_real_vn100")
needs_real_log = pytest.mark.skipif(
    not real_vn100.LOGS.exists(), reason=f"real VN-100 log not present ({real_vn100.LOGS})"
)


@needs_real_log
@pytest.mark.parametrize("seed", [0, 1])
def test_real_binary_log_decodes_every_value_as_its_authors_did(seed):
    """A real VN-100 (IMU + Attitude groups, 10 Hz) written to an SD card between NMEA lines
    and a logger's text: every packet, every one of its 29 values, against the authors' CSV."""
    r = real_vn100.compare("F00379", seed=seed)
    print(r)
    assert r["packets_accepted"] == 8895 and r["crc_rejected"] == 2  # real corruption
    assert r["imu_samples"] == 8895  # the gyro comes from Imu.UncompGyro
    assert r["malformed"] == 0 and r["other_ascii_lines"] == 3748  # NMEA lines: not errors
    assert r["upstream_rows_matched"] == r["upstream_rows"] == 8895
    assert r["values_compared"] == 8895 * 29
    assert r["max_rel_diff"] <= 5.01e-7  # half a unit in the 7th printed digit


@needs_real_log
def test_real_short_log_all_packets_valid():
    r = real_vn100.compare("F00294")
    assert r["packets_accepted"] == r["imu_samples"] == 99 and r["crc_rejected"] == 0
    # the authors' CSV lacks one packet (78) that is CRC-valid; every other row matches
    assert r["upstream_rows_matched"] == r["upstream_rows"] == 98
    assert r["packets_not_in_upstream_csv"] == [78]
    assert r["max_rel_diff"] <= 5.01e-7


def test_field_sizes_follow_the_manuals():
    size = binary.field_size
    assert size(1, 8) == 4 and size(1, 9) == 1  # Time.SyncOutCnt, Time.TimeStatus
    assert size(3, 12) == 2 and size(3, 13) == 28  # Gnss.TimeInfo, Gnss.Dop
    assert size(4, 12) == 12  # Attitude.Heave
    assert all(size(6, b) == size(3, b) for b in range(16))  # GNSS2 = GNSS
    assert [size(0, b) for b in range(15)] == [8, 8, 8, 12, 16, 12, 24, 12, 12, 24, 20, 28, 2, 4, 8]
    imu = [2, 12, 12, 12, 4, 4, 16, 12, 12, 12, 12, 2, 40]
    assert [size(2, b) for b in range(13)] == imu


_FIXED = [name for name, (g, b) in binary.FIELD_INDEX.items() if not binary.FIELDS[(g, b)].variable]


@settings(max_examples=300)
@given(
    st.lists(st.sampled_from(sorted(binary.FIELD_INDEX)), min_size=1, max_size=12, unique=True),
    st.randoms(use_true_random=False),
    st.integers(1, 64),
)
def test_any_field_combination_is_framed_and_split_exactly(names, rnd, chunk):
    """Whatever fields a user enables, in any groups: the packet is found, every field at
    its place, whatever the chunking, with garbage around it."""
    fields = {}
    for name in names:
        spec = binary.FIELDS[binary.FIELD_INDEX[name]]
        if spec.variable == "satinfo":
            n = rnd.randint(0, 5)
            fields[name] = bytes([n, 0]) + rnd.randbytes(8 * n)
        elif spec.variable == "rawmeas":
            n = rnd.randint(0, 3)
            fields[name] = rnd.randbytes(10) + bytes([n, 0]) + rnd.randbytes(28 * n)
        else:
            fields[name] = rnd.randbytes(spec.size)
    pkt = binary.encode_packet(fields)
    stream = b"junk$GP" + pkt + b"\r\nM,123\r\n" + pkt
    p = Vn100Parser()
    out = []
    for k in range(0, len(stream), chunk):
        out += p.feed(stream[k : k + chunk])
    packets = [o for o in out if isinstance(o, BinaryPacket)]
    assert len(packets) == 2, p.stats.as_dict()
    for got in packets:
        assert set(got.field_names) == set(fields)
        for name, data in fields.items():
            assert got.raw(name) == data
            got.get(name)  # every field decodes


def test_reserved_bit_is_refused_named_and_the_stream_goes_on():
    good = binary.encode_packet({"Common.AngularRate": struct.pack("<3f", 1, 2, 3)})
    body = bytes([0x04]) + struct.pack("<H", (1 << 10) | (1 << 14)) + bytes(12)
    odd = b"\xfa" + body + struct.pack(">H", crc16(body))  # Imu bit 14: no manual sizes it
    p = Vn100Parser()
    out = p.feed(odd + good + odd + good)
    assert len(out) == 2 and all(np.allclose(o["Common.AngularRate"], [1, 2, 3]) for o in out)
    assert p.stats.unknown_field == 2 and p.stats.unknown_field_bits == {"Imu bit 14": 2}


def test_false_sync_claiming_a_long_packet_does_not_hold_back_real_ones():
    """0xFA + GNSS SatInfo with 255 satellites in garbage would claim 2 KB; the real packets
    right behind it are delivered at once, not after 2 KB more of the line."""
    good = binary.encode_packet({"Common.AngularRate": struct.pack("<3f", 1, 2, 3)})
    fake = b"\xfa\x08" + struct.pack("<H", 1 << 14) + bytes([255, 0])
    p = Vn100Parser()
    out = p.feed(fake + good + good)
    assert len(out) == 2 and p.stats.bad_binary_header == 1


@pytest.mark.parametrize(
    ("fields", "source", "expect"),
    [
        ({"Common.AngularRate": (0.1, 0.2, 0.3)}, "auto", (0.1, 0.2, 0.3)),
        ({"Imu.UncompGyro": (0.1, 0.2, 0.3)}, "auto", (0.1, 0.2, 0.3)),
        ({"Imu.UncompGyro": (0.1, 0.2, 0.3)}, "angular_rate", None),
        ({"Imu.AngularRate": (1, 1, 1), "Imu.UncompGyro": (2, 2, 2)}, "uncomp_gyro", (2, 2, 2)),
        ({"Imu.AngularRate": (1, 1, 1), "Imu.UncompGyro": (2, 2, 2)}, "auto", (1, 1, 1)),
        ({"Common.Imu": (0, 0, -9.8, 0.1, 0.2, 0.3)}, "uncomp_gyro", (0.1, 0.2, 0.3)),
        ({"Imu.DeltaTheta": (0.01, 0.5, -1.0, 2.0)}, "auto", np.radians([50, -100, 200])),
        ({"Common.Deltas": (0.02, 1, 1, 1, 0, 0, 0)}, "delta_theta", np.radians([50] * 3)),
        ({"Attitude.YawPitchRoll": (10, 0, 0)}, "auto", None),
    ],
)
def test_gyro_from_whichever_field_the_sensor_sends(fields, source, expect):
    pkt = binary.encode_packet({k: binary.pack_values(k, v) for k, v in fields.items()})
    (item,) = Vn100Parser().feed(pkt)
    ex = ImuExtractor(source)
    s = ex.sample(item, 5_000_000_000)
    if expect is None:
        assert s is None and ex.stats.unused == 1
    else:
        assert np.allclose(s.gyro, expect, rtol=1e-6) and ex.stats.samples == 1


@pytest.mark.parametrize(
    "fields",
    [
        {"Common.Deltas": (0.02, 1, 1, 1, 0.0, 0.01, -0.1962)},
        {"Imu.DeltaTheta": (0.02, 1, 1, 1), "Imu.DeltaVel": (0.0, 0.01, -0.1962)},
        {"Imu.DeltaTheta": (0.02, 1, 1, 1), "Common.Accel": (0.0, 0.5, -9.81)},
    ],
    ids=["Deltas", "DeltaTheta+DeltaVel", "DeltaTheta+Accel"],
)
def test_an_integrated_rate_comes_with_the_integrated_velocity_over_the_same_interval(fields):
    """Δθ/Δt is the mean rate over an output interval; the acceleration that belongs with it
    is Δv/Δt over the same interval (not the last instant's), when the packet has Δv."""
    pkt = binary.encode_packet({k: binary.pack_values(k, v) for k, v in fields.items()})
    (item,) = Vn100Parser().feed(pkt)
    s = ImuExtractor("delta_theta").sample(item, 5_000_000_000)
    assert np.allclose(s.gyro, np.radians([50.0] * 3), rtol=1e-6)
    assert np.allclose(s.accel, (0.0, 0.5, -9.81), rtol=1e-5)


def test_ascii_delta_message_gives_the_mean_specific_force():
    body = b"VNDTV,+0.020000,+1.0000,+1.0000,+1.0000,+0.0000,+0.0100,-0.1962"
    (msg,) = Vn100Parser().feed(b"$" + body + b"*%02X\r\n" % xor8(body))
    s = ImuExtractor("delta_theta").sample(msg, 1_000_000_000)
    assert np.allclose(s.gyro, np.radians([50.0] * 3)) and np.allclose(s.accel, (0, 0.5, -9.81))


_RATE = (0.01, -0.02, 0.03)
_MAG, _ACC, _W = (
    "+00.2000,+00.0500,+00.4500",
    "+00.000,+00.000,-09.810",
    "+00.010000,-00.020000,+00.030000",
)
ASCII_OUTPUTS = {
    b"VNYPR,+010.000,-001.000,+002.000": None,
    b"VNQTN,+0.000000,+0.000000,+0.087156,+0.996195": None,
    f"VNMAG,{_MAG}".encode(): None,
    f"VNACC,{_ACC}".encode(): None,
    f"VNGYR,{_W}".encode(): _RATE,
    f"VNMAR,{_MAG},{_ACC},{_W}".encode(): _RATE,
    b"VNDTV,+0.010000,+0.5000,-1.0000,+2.0000,+0.0000,+0.0000,-0.0981": tuple(
        np.radians([50, -100, 200])
    ),
    f"VNIMU,{_MAG},{_ACC},{_W},+25.0,+101.3".encode(): _RATE,
    b"VNGPS,342123.000,1234,3,08,+37.0,-122.0,+0010.0,+000.0,+000.0,+000.0,"
    b"+002.0,+002.0,+005.0,+0.0,1.0E-08": None,
    b"VNINS,342123.000,1234,0000,+37.0,-122.0,+0010.0,+000.0,+000.0,+000.0,"
    b"+0.0,+0.0,+0.0,+0.0,+0.0": None,
    b"VNHVE,+0.010,+0.002,+0.000": None,
}


@pytest.mark.parametrize("body", list(ASCII_OUTPUTS), ids=lambda b: b[:5].decode())
def test_every_ascii_output_type_is_recognised(body):
    """A valid message the runtime does not use is `unused`: never malformed, never garbage."""
    p = Vn100Parser()
    (msg,) = p.feed(b"$" + body + b"*%02X\r\n" % xor8(body))
    assert p.stats.rejected == 0 and p.stats.other_ascii == 0
    ex = ImuExtractor()
    s = ex.sample(msg, 1_000_000_000)
    expect = ASCII_OUTPUTS[body]
    if expect is None:
        assert s is None and ex.stats.unused == 1
    else:
        assert np.allclose(s.gyro, expect)


def test_other_devices_lines_and_unchecked_lines():
    nmea = b"GPRMC,000012.800,V,,,,,0.00,0.00,060180,,,N"
    p = Vn100Parser()
    out = p.feed(b"$" + nmea + b"*%02X\r\n" % xor8(nmea) + b"$" + YMR_A + b"*XX\r\n")
    assert len(out) == 1 and out[0].header == "GPRMC" and not out[0].known
    assert p.stats.other_ascii == 1 and p.stats.malformed == 0
    assert p.stats.unchecked == 1  # a sensor with error detection off is never trusted


@needs_real_log
def test_real_log_gives_the_magnetic_field_and_a_steady_levelled_direction():
    """The compass's input from a real VN-100 (issue 18): every sample carries the field in
    tesla (the authors' gauss / 10⁴), and levelled with the sensor's own specific force the
    field's direction follows the sensor's yaw up to one constant (its uncompensated
    offset) — within 2° for half the samples of a 15-minute log on moving sea ice."""
    raw = (real_vn100.LOGS / "raw" / "F00294").read_bytes()
    items = Vn100Parser().feed(raw)
    ref = real_vn100.read_upstream_csv(real_vn100.LOGS / "parsed_by_upstream" / "F00294_B")
    samples = [s for k, it in enumerate(items) if (s := ImuExtractor().sample(it, k)) is not None]
    mags = np.array([s.mag for s in samples if s.mag is not None])
    assert len(mags) == len(samples) == 99
    rows = [k for k in range(99) if k != 78]  # the one packet the authors' CSV lacks
    np.testing.assert_allclose(mags[rows] * 1e4, ref[:, 0:3], rtol=1e-6)
    r = real_vn100.compass("F00379")
    print(r)
    assert r["levelled"]["samples"] == 8895
    assert r["levelled"]["spread_deg_p50"] < 2.0 and r["levelled"]["spread_deg_p95"] < 8.0


@pytest.mark.parametrize(("sent_hz", "warned"), [(400, True), (50, False)])
def test_a_sensor_far_from_its_configured_rate_is_named_once(sent_hz, warned, caplog):
    """A VN-100 that keeps its own output (``imu.configure_sensor: false``) may send at
    another rate than ``imu.rate_hz``: after five seconds of its samples the driver says so,
    once, with both rates (the staleness limit is judged against the configured one)."""
    from drivers.imu.vn100 import Vn100

    source = still_source(0.0)
    mock = MockVn100("unused-link")  # not started: only its packets
    mock.registers[75] = ["1", "8", "01", "0129"]
    drv = Vn100("unused", rate_hz=50, configure_sensor=False)  # not started: fed directly
    for k in range(7 * sent_hz):
        drv.feed(mock._binary_packet(k / sent_hz, source), int(k * 1e9 / sent_hz))
    assert drv.stats.samples >= 6 * sent_hz
    said = [r.getMessage() for r in caplog.records if "samples a second" in r.getMessage()]
    if warned:
        assert len(said) == 1 and "sends 400 samples a second, imu.rate_hz says 50" in said[0]
        assert "imu.configure_sensor false" in said[0]
    else:
        assert said == []
