"""The DBC, the CRC and the codec: inputs -> SI samples, publications -> checked frames."""

import math
import re
import struct
from pathlib import Path

import cantools
import numpy as np
import pytest
from crccheck.crc import Crc8SaeJ1850

from online_id.errors import ConfigError, DbcError, InputDataError
from online_id.io.crc import CHECK, crc8_j1850
from online_id.io.dbc import BenchCommand, CommandSample, InputDecoder, RoleMapping, RoleSignal, default_dbc_path, encode_inputs, load_dbc
from online_id.io.dbc_output import OUTPUT_MESSAGES, OutputEncoder
from online_id.records import (
    ROLES,
    AlertKind,
    AlertOut,
    EstimateOut,
    ExcitationOut,
    FrameFault,
    QualityOut,
    ServiceState,
    SignalSample,
    StatusOut,
)

REPO_DBC = Path(__file__).resolve().parent.parent / "dbc" / "online_id.dbc"
RPM = math.pi / 30.0

# A bench's own DBC: one message packs all roles (big-endian, rad/s, torque positive = driving),
# a multiplexed message, and an IEEE float torque (for NOT_FINITE).
BENCH_DBC = """VERSION ""

BU_: Bench Oid

BO_ 512 BenchData: 8 Bench
 SG_ ShaftSpeedA : 7|16@0- (0.01,0) [-300|300] "rad/s" Oid
 SG_ ShaftSpeedB : 23|16@0- (0.01,0) [-300|300] "rad/s" Oid
 SG_ LoadTorque : 39|16@0- (0.1,0) [-3000|3000] "N.m" Oid
 SG_ Alive : 55|8@0+ (1,0) [0|255] "" Oid

BO_ 513 FloatTorque: 8 Bench
 SG_ TorqueF : 0|32@1- (1,0) [-3000|3000] "Nm" Oid

BO_ 514 Paged: 8 Bench
 SG_ Page M : 0|8@1+ (1,0) [0|1] "" Oid
 SG_ PagedSpeed m0 : 8|32@1- (0.001,0) [-1000|1000] "rpm" Oid
 SG_ PagedTemp m1 : 8|16@1+ (1,0) [0|100] "degC" Oid

SIG_VALTYPE_ 513 TorqueF : 1;
"""

BENCH_MAPPING = RoleMapping(
    dyno_speed=RoleSignal("BenchData", "ShaftSpeedA", "rad/s", 1, "Alive"),
    engine_speed=RoleSignal("BenchData", "ShaftSpeedB", "rad/s", 1, "Alive"),
    dyno_torque=RoleSignal("BenchData", "LoadTorque", "Nm", -1, "Alive"),
    command=None,
)


@pytest.fixture(scope="module")
def db():
    return load_dbc()


@pytest.fixture(scope="module")
def bench_db(tmp_path_factory):
    path = tmp_path_factory.mktemp("dbc") / "bench.dbc"
    path.write_text(BENCH_DBC)
    return load_dbc(path)


# --- the DBC file ----------------------------------------------------------------------


def test_dbc_loads_strictly_and_packaged_copy_is_identical(db):
    assert default_dbc_path().read_bytes() == REPO_DBC.read_bytes()
    strict = cantools.database.load_file(str(REPO_DBC), strict=True)
    assert {m.name: m.frame_id for m in strict.messages} == {
        "DynoSpeed": 0x101, "EngineSpeed": 0x102, "DynoTorque": 0x103, "OidCommand": 0x120,
        "OidEstimate": 0x300, "OidShaft": 0x301, "OidQuality": 0x302, "OidStatus": 0x303,
        "OidAlert": 0x304, "OidExcitation": 0x305, "OidFreshness": 0x306,
    }
    for msg in db.messages:
        assert msg.length == 8 and not msg.is_extended_frame
        assert msg.comment, msg.name
        for sig in msg.signals:
            assert sig.comment, f"{msg.name}.{sig.name} has no CM_"


def test_every_output_has_a_4_bit_counter_and_a_crc_in_byte_7(db):
    for name in OUTPUT_MESSAGES.values():
        msg = db.get_message_by_name(name)
        counter = msg.get_signal_by_name(f"{name}Counter")
        crc = msg.get_signal_by_name(f"{name}CRC")
        assert (counter.length, counter.minimum, counter.maximum) == (4, 0, 15)
        assert (crc.start, crc.length, crc.byte_order) == (56, 8, "little_endian")


def test_enums_match_the_record_types(db):
    assert db.get_message_by_name("OidStatus").get_signal_by_name("State").choices == {
        s.value: s.name for s in ServiceState}
    assert db.get_message_by_name("OidAlert").get_signal_by_name("AlertKind").choices == {
        k.value: k.name for k in AlertKind}
    assert db.get_message_by_name("OidCommand").get_signal_by_name("Command").choices == {
        c.value: c.name for c in BenchCommand}


@pytest.mark.parametrize("message, limit", [("DynoSpeed", 10000), ("EngineSpeed", 10000), ("DynoTorque", 3000)])
def test_input_scalings_cover_the_range(db, message, limit):
    sig = db.get_message_by_name(message).get_signal_by_name(message)
    raw_max = 2 ** (sig.length - 1) - 1
    assert sig.is_signed and sig.scale == 0.0001
    assert (sig.minimum, sig.maximum) == (-limit, limit)
    assert raw_max * sig.scale >= limit and -(raw_max + 1) * sig.scale <= -limit


def test_csv_values_with_4_decimals_round_trip_exactly(db):
    rng = np.random.default_rng(1)
    n = 3000
    t = np.arange(n) / 1000.0
    cols = [np.array([float(f"{v:.4f}") for v in rng.uniform(lo, hi, n)])
            for lo, hi in ((-10000, 10000), (-10000, 10000), (-3000, 3000))]
    cols[0][:2] = cols[1][:2] = 10000.0, -10000.0  # the range limits themselves
    cols[2][:2] = 3000.0, -3000.0
    frames = encode_inputs(t, *cols, db=db)
    dec = InputDecoder(db)
    got = {role: [] for role in ROLES}
    for t_s, fid, data in frames:
        (s,) = dec.decode(fid, data, t_s)
        got[s.role].append(s)
    for role, col in zip(ROLES, cols):
        values = np.array([s.value for s in got[role]])
        factor = 1.0 if role == "dyno_torque" else RPM
        assert np.array_equal(values, col * factor)  # exact, not approximately
        assert [s.counter for s in got[role]] == [i % 256 for i in range(n)]
        assert [s.t_s for s in got[role]] == list(t)


# --- CRC ------------------------------------------------------------------------------------


def test_crc_check_value_and_crccheck_agree():
    assert crc8_j1850(b"123456789") == CHECK == 0x4B
    assert crc8_j1850(b"") == Crc8SaeJ1850.calc(b"")
    rng = np.random.default_rng(2)
    for n in range(1, 40):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert crc8_j1850(data) == Crc8SaeJ1850.calc(data)


# --- output frames -------------------------------------------------------------------------


def _publications():
    return [
        EstimateOut(1.0, 16.31, 0.0473, 6012.5, 3.21, True),
        QualityOut(1.0, 0.0051, 0.0051 ** 2 * 1.1, 21.3, 1234),
        StatusOut(1.0, ServiceState.TRACKING, 3, 7),
        AlertOut(1.0, AlertKind.FREQ_DRIFT, 1, -4.25, 1600.0, "f0 -4.25 %"),
        ExcitationOut(1.0, -25.5, True),
    ]


def test_output_frames_verify_and_decode_back(db):
    enc = OutputEncoder(db)
    frames = [f for pub in _publications() for f in enc.encode(pub)]
    assert [fid for fid, _ in frames] == [0x300, 0x301, 0x302, 0x303, 0x304, 0x305]
    for fid, data in frames:
        assert len(data) == 8 and enc.verify(fid, data)
    est, shaft, qual, status, alert, exc = (enc.decode(fid, data) for fid, data in frames)
    assert est["ResonanceFreq"] == pytest.approx(16.31, abs=0.001) and est["Valid"] == 1
    assert est["DampingRatio"] == pytest.approx(0.0473, abs=1e-5)
    assert shaft["ShaftStiffness"] == pytest.approx(6012.5, abs=0.01) and shaft["ShaftDamping"] == 3.21
    assert qual["ResidualRms"] == pytest.approx(0.0051) and qual["SamplesUsed"] == 1234
    assert qual["Fpe"] == pytest.approx(0.0051 * math.sqrt(1.1), abs=1e-4)
    assert (status["State"], status["BadFrames"], status["MissingFrames"]) == (2, 3, 7)
    assert (alert["AlertKind"], alert["Severity"], alert["DriftPct"], alert["SpeedRpm"]) == (1, 1, -4.25, 1600)
    assert (exc["TorqueOffset"], exc["Active"]) == (-25.5, 1)
    # consumers with plain cantools see the same values
    assert db.decode_message(0x303, frames[3][1], decode_choices=True)["State"] == "TRACKING"


def test_corrupted_byte_fails_verify(db):
    enc = OutputEncoder(db)
    for fid, data in (f for pub in _publications() for f in enc.encode(pub)):
        for i in range(8):
            for bit in range(8):
                bad = bytearray(data)
                bad[i] ^= 1 << bit
                assert not enc.verify(fid, bytes(bad))
        assert not enc.verify(fid, data[:7]) and not enc.verify(0x7FF, data)


def test_counters_wrap_0_to_15_per_message(db):
    enc = OutputEncoder(db)
    seen = {"status": [], "excitation": []}
    for i in range(40):
        fid, data = enc.encode(StatusOut(i, ServiceState.LEARNING, i, 0))[0]
        seen["status"].append(enc.decode(fid, data)["OidStatusCounter"])
        if i % 2:
            fid, data = enc.encode(ExcitationOut(i, 1.0, True))[0]
            seen["excitation"].append(enc.decode(fid, data)["OidExcitationCounter"])
    assert seen["status"] == [i % 16 for i in range(40)]
    assert seen["excitation"] == [i % 16 for i in range(20)]


def test_values_saturate_and_non_finite_clears_valid(db):
    enc = OutputEncoder(db)
    est, shaft = (enc.decode(*f) for f in enc.encode(EstimateOut(0, 500.0, math.nan, 1e9, -3.0, True)))
    assert est["ResonanceFreq"] == pytest.approx(131.07) and est["DampingRatio"] == 0 and est["Valid"] == 0
    assert shaft["ShaftStiffness"] == pytest.approx(335544.3) and shaft["ShaftDamping"] == 0
    assert shaft["Valid"] == 1
    status = enc.decode(*enc.encode(StatusOut(0, ServiceState.FAULT, 10 ** 6, 70000))[0])
    assert (status["BadFrames"], status["MissingFrames"]) == (65535, 65535)
    with pytest.raises(TypeError):
        enc.encode(SignalSample("dyno_speed", 1.0, 0.0))



def test_every_output_value_is_clamped_to_what_its_signal_carries(db, tmp_path):
    """Frames are encoded without cantools' strict check: any value, in or far out of range, gives the clamped
    value back, never a wrapped bit pattern; also for a DBC whose declared range exceeds the signal's bits."""
    text = default_dbc_path().read_text().replace("[0|131.07]", "[-50|1000]")  # ResonanceFreq, 16 bits x 0.002
    assert text != default_dbc_path().read_text()
    (tmp_path / "wide.dbc").write_text(text)
    rng = np.random.default_rng(4)
    for dbx in (db, load_dbc(tmp_path / "wide.dbc")):
        enc = OutputEncoder(dbx)
        for key, name in OUTPUT_MESSAGES.items():
            msg = dbx.get_message_by_name(name)
            for _ in range(200):
                values = {sig.name: float(rng.choice([rng.uniform(-1e6, 1e6), rng.uniform(-10, 10), 0.0, 1e300,
                                                      -math.inf, math.nan]))
                          for sig in msg.signals}
                fid, data = enc._encode(key, values)
                back = enc.decode(fid, data)
                for sig in msg.signals:
                    if sig.name in (f"{name}Counter", f"{name}CRC"):
                        continue
                    v = values[sig.name] if math.isfinite(values[sig.name]) else 0.0
                    raw_hi = (1 << sig.length) - 1 if not sig.is_signed else (1 << (sig.length - 1)) - 1
                    raw_lo = 0 if not sig.is_signed else -(1 << (sig.length - 1))
                    lo = max(sig.minimum if sig.minimum is not None else -math.inf, sig.offset + sig.scale * raw_lo)
                    hi = min(sig.maximum if sig.maximum is not None else math.inf, sig.offset + sig.scale * raw_hi)
                    assert back[sig.name] == pytest.approx(min(max(v, lo), hi), abs=sig.scale), (name, sig.name, v)


# --- input decoding: every fault kind -------------------------------------------------------


def _crc(seven: bytes) -> bytes:
    return seven + bytes([crc8_j1850(seven)])


def _speed(rpm_raw: int, counter: int = 0) -> bytes:
    return struct.pack("<iB3x", rpm_raw, counter)


def test_decode_sample_command_and_every_fault(db, bench_db):
    dec = InputDecoder(db)
    (s,) = dec.decode(0x101, _speed(12_345_678, 9), 2.5)
    assert s == SignalSample("dyno_speed", 1234.5678 * RPM, 2.5, 9)
    cmd = dec.decode(0x120, _crc(bytes([3, 17, 0, 1, 2, 3, 4])), 3.0)
    assert cmd == CommandSample(BenchCommand.RESET_ESTIMATOR, 3.0, 17, bytes([1, 2, 3, 4]))  # freshness, MAC
    rng = np.random.default_rng(3)
    for fid in rng.integers(0, 0x800, 200):
        if int(fid) not in (0x101, 0x102, 0x103, 0x120):
            assert dec.decode(int(fid), bytes(8), 0.0) is FrameFault.UNKNOWN_ID
    assert dec.decode(0x101, _speed(0), 0.0, is_extended=True) is FrameFault.UNKNOWN_ID
    for data in (b"", bytes(7), bytes(9), None):
        assert dec.decode(0x101, data, 0.0) is FrameFault.BAD_DLC
    assert dec.decode(0x101, _speed(100_000_001), 0.0) is FrameFault.OUT_OF_RANGE
    assert 'Expected signal "DynoSpeed"' in dec.last_fault and "10000.0001" in dec.last_fault
    assert dec.decode(0x101, _speed(-100_000_000), 0.0) != FrameFault.OUT_OF_RANGE  # the limit itself is fine
    assert dec.decode(0x103, _speed(30_000_001), 0.0) is FrameFault.OUT_OF_RANGE
    assert dec.decode(0x120, _crc(bytes([4] + [0] * 6)), 0.0) is FrameFault.OUT_OF_RANGE
    assert dec.decode(0x120, bytes([3, 18] + [0] * 6), 4.0) is FrameFault.COMMAND_REFUSED  # no CRC

    mapping = RoleMapping(
        dyno_speed=RoleSignal("Paged", "PagedSpeed", "rpm", 1, None),
        engine_speed=RoleSignal("BenchData", "ShaftSpeedB", "rad/s"),
        dyno_torque=RoleSignal("FloatTorque", "TorqueF", "Nm"),
        command=None,
    )
    dec = InputDecoder(bench_db, mapping)
    assert dec.decode(514, bytes([7] + [0] * 7), 0.0) is FrameFault.MALFORMED  # unknown multiplexer page
    assert dec.decode(514, bytes([1, 20] + [0] * 6), 0.0) == []  # page without a mapped role
    (s,) = dec.decode(514, bytes([0]) + struct.pack("<i", 900_000) + bytes(3), 1.0)
    assert s.value == pytest.approx(900 * RPM)
    for bad in (math.nan, math.inf, -math.inf):
        assert dec.decode(513, struct.pack("<f", bad) + bytes(4), 0.0) is FrameFault.NOT_FINITE
    assert dec.decode(513, struct.pack("<f", 3500.0) + bytes(4), 0.0) is FrameFault.OUT_OF_RANGE
    (s,) = dec.decode(513, struct.pack("<f", -12.5) + bytes(4), 0.0)
    assert s == SignalSample("dyno_torque", -12.5, 0.0, None)


def test_bench_dbc_with_other_names_packing_all_roles(bench_db):
    n = 500
    t = np.arange(n) * 0.002
    rpm = np.linspace(-2000, 2800, n)
    torque = np.linspace(-2900, 2900, n)
    frames = encode_inputs(t, rpm, rpm / 2, torque, db=bench_db, mapping=BENCH_MAPPING)
    assert len(frames) == n and {fid for _, fid, _ in frames} == {512}
    ref = bench_db.get_message_by_name("BenchData")
    dec = InputDecoder(bench_db, BENCH_MAPPING)
    for i, (t_s, fid, data) in enumerate(frames):
        raw = ref.decode(data)
        assert raw["LoadTorque"] == pytest.approx(-torque[i], abs=0.05)  # bench: positive = driving
        samples = dec.decode(fid, data, t_s)
        assert [s.role for s in samples] == list(ROLES)
        assert {s.counter for s in samples} == {i % 256}
        dyno, engine, load = (s.value for s in samples)
        assert dyno == pytest.approx(rpm[i] * RPM, abs=0.005)
        assert engine == pytest.approx(rpm[i] / 2 * RPM, abs=0.005)
        assert load == pytest.approx(torque[i], abs=0.05)


def test_decoder_never_raises_on_random_frames(db, bench_db):
    rng = np.random.default_rng(4)
    decoders = [InputDecoder(db), InputDecoder(bench_db, BENCH_MAPPING)]
    ids = [0x101, 0x102, 0x103, 0x120, 512, 513, 514]
    kinds = set()
    for _ in range(10_000):
        fid = int(rng.choice(ids)) if rng.random() < 0.7 else int(rng.integers(0, 0x20000000))
        data = rng.integers(0, 256, int(rng.choice([8, 8, 8, 0, 3, 7, 9, 64])), dtype=np.uint8).tobytes()
        for dec in decoders:
            out = dec.decode(fid, data, 0.0, is_extended=bool(rng.random() < 0.1))
            assert isinstance(out, (list, CommandSample, FrameFault))
            kinds.add(type(out).__name__ if not isinstance(out, FrameFault) else out.name)
            if isinstance(out, list):
                assert all(isinstance(s, SignalSample) and math.isfinite(s.value) for s in out)
    # random command frames fail the CRC (1 in 256 passes it, then the value must be 0..3)
    assert {"list", "COMMAND_REFUSED", "UNKNOWN_ID", "BAD_DLC", "OUT_OF_RANGE"} <= kinds


# --- errors that name file, message and signal ------------------------------------------------


def test_mapping_errors_list_what_exists(db):
    with pytest.raises(DbcError, match=r'expected a message "Speeds".*DynoSpeed, DynoTorque'):
        InputDecoder(db, RoleMapping(dyno_speed=RoleSignal("Speeds", "DynoSpeed", "rpm")), source="x.dbc")
    with pytest.raises(DbcError, match=r'x.dbc: expected a signal "Rpm".*"DynoSpeed".*DynoSpeedCounter'):
        InputDecoder(db, RoleMapping(dyno_speed=RoleSignal("DynoSpeed", "Rpm", "rpm")), source="x.dbc")
    with pytest.raises(DbcError, match="expected unit 'rad/s'.*says 'rpm'"):
        InputDecoder(db, RoleMapping(dyno_speed=RoleSignal("DynoSpeed", "DynoSpeed", "rad/s")))
    with pytest.raises(ConfigError, match="unit"):
        RoleMapping(dyno_torque=RoleSignal("DynoTorque", "DynoTorque", "rpm"))
    with pytest.raises(ConfigError, match="sign"):
        RoleSignal("DynoTorque", "DynoTorque", "Nm", sign=2)
    with pytest.raises(DbcError, match=r"expected a signal \"OidCommandCounter\".*in message \"OidCommand\""):
        OutputEncoder(db, {"status": "OidCommand"})


def test_load_dbc_errors_name_file_and_line(tmp_path):
    bad = tmp_path / "bad.dbc"
    bad.write_text(BENCH_DBC.replace(" SG_ Alive : 55", " SG_ Alive 55"))
    with pytest.raises(DbcError) as info:
        load_dbc(bad)
    msg = str(info.value)
    assert msg.startswith(f"{bad}:9: invalid DBC syntax") and "\n" not in msg
    overlap = tmp_path / "overlap.dbc"
    overlap.write_text(BENCH_DBC.replace("SG_ Alive : 55|8", "SG_ Alive : 60|8"))
    with pytest.raises(DbcError, match=rf"{overlap}: not a usable DBC file: .*Alive"):
        load_dbc(overlap)
    with pytest.raises(DbcError, match="missing.dbc: cannot read"):
        load_dbc(tmp_path / "missing.dbc")


def test_encode_inputs_rejects_out_of_range_and_supports_rates(db):
    t = np.arange(300) / 1000.0
    speed = np.full(300, 1000.0)
    torque = np.zeros(300)
    speed_bad = speed.copy()
    speed_bad[17] = 10001.0
    with pytest.raises(InputDataError, match=r'sample 17 \(t = 0.017 s\).*"DynoSpeed".*10001'):
        encode_inputs(t, speed_bad, speed, torque, db=db)
    frames = encode_inputs(t, speed, speed, torque, db=db, decimation={"dyno_torque": 3},
                           jitter_s=200e-6, seed=7)
    by_id = {fid: [f for f in frames if f[1] == fid] for fid in (0x101, 0x102, 0x103)}
    assert [len(v) for v in by_id.values()] == [300, 300, 100]
    times = [f[0] for f in frames]
    assert times == sorted(times)
    delays = np.array([f[0] for f in by_id[0x103]]) - t[::3]
    assert 0 <= delays.min() and delays.max() < 200e-6 and delays.std() > 0
    with pytest.raises(ConfigError, match="decimation"):
        encode_inputs(t, speed, speed, torque, db=db, decimation={"dyno_torque": 0})


# --- the receive loop's fast paths: the same bytes and values as cantools --------------------------------------------

# output messages of another layout: big-endian and signed signals, offsets, signals across bytes out of order, and
# a float one (which cantools encodes: no fast packer); they replace those of online_id.dbc, the others stay
OTHER_OUTPUTS = """BO_ 768 OidEstimate: 8 OnlineId
 SG_ ResonanceFreq : 7|16@0+ (0.002,0) [0|131.07] "Hz" Bench
 SG_ DampingRatio : 18|13@1- (1e-04,0.1) [-0.3|0.5] "" Bench
 SG_ Valid : 31|1@1+ (1,0) [0|1] "" Bench
 SG_ OidEstimateCounter : 51|4@0+ (1,0) [0|15] "" Bench
 SG_ OidEstimateCRC : 56|8@1+ (1,0) [0|255] "" Bench

BO_ 769 OidShaft: 8 OnlineId
 SG_ ShaftStiffness : 0|32@1- (1,0) [-1e6|1e6] "Nm/rad" Bench
 SG_ ShaftDamping : 32|16@1- (0.01,0) [-300|300] "Nms/rad" Bench
 SG_ Valid : 48|1@1+ (1,0) [0|1] "" Bench
 SG_ OidShaftCounter : 52|4@1+ (1,0) [0|15] "" Bench
 SG_ OidShaftCRC : 56|8@1+ (1,0) [0|255] "" Bench

BO_ 770 OidQuality: 8 OnlineId
 SG_ ResidualRms : 0|32@1- (1,0) [-1e9|1e9] "rad/s" Bench
 SG_ Fpe : 32|12@1+ (0.0001,0) [0|0.4095] "rad/s" Bench
 SG_ Excitation : 44|4@1+ (100,0) [0|1500] "Nm" Bench
 SG_ SamplesUsed : 48|4@1+ (1,0) [0|15] "" Bench
 SG_ OidQualityCounter : 52|4@1+ (1,0) [0|15] "" Bench
 SG_ OidQualityCRC : 56|8@1+ (1,0) [0|255] "" Bench
"""


def _other_outputs_dbc(path: Path) -> Path:
    text = default_dbc_path().read_text()
    for fid in (768, 769, 770):
        text, n = re.subn(rf"^BO_ {fid} .*\n(?: SG_ .*\n)*", "", text, flags=re.MULTILINE)
        assert n == 1
    path.write_text(text.replace("\nCM_ ", "\n" + OTHER_OUTPUTS + "\nCM_ ", 1) + "\nSIG_VALTYPE_ 770 ResidualRms : 1;\n")
    return path


def test_output_frames_are_the_bytes_cantools_encodes(db, tmp_path):
    """The encoder packs bits itself (the receive loop's budget); every frame is byte for byte what cantools
    encodes from the same clamped values, on this DBC and on one with big-endian, signed, offset, unaligned and
    float signals; a message with a float signal is left to cantools."""
    other = load_dbc(_other_outputs_dbc(tmp_path / "other.dbc"))
    rng = np.random.default_rng(11)
    for dbx in (db, other):
        enc = OutputEncoder(dbx)
        packed = [k for k in OUTPUT_MESSAGES if enc._specs[k].packer is not None]
        assert packed == [k for k in OUTPUT_MESSAGES if k != "quality" or dbx is db]  # the float message has none
        for key in OUTPUT_MESSAGES:
            spec = enc._specs[key]
            for _ in range(300):
                values = {sig.name: float(rng.choice([rng.uniform(-1e6, 1e6), rng.uniform(-2, 2), 0.0, 1e300,
                                                      rng.uniform(0, 200), -math.inf, math.nan]))
                          for sig in spec.message.signals}
                count = enc._count[key]
                fid, data = enc._encode(key, values)
                phys = {name: (min(max(v, lo), hi) if math.isfinite(v := float(values[name]))
                               else min(max(0.0, lo), hi)) for name, (lo, hi) in spec.bounds.items()}
                phys[spec.counter], phys[spec.crc] = count, 0
                want = bytearray(spec.message.encode(phys, scaling=True, padding=False, strict=False))
                want[7] = crc8_j1850(want[:7])
                assert (fid, data) == (spec.message.frame_id, bytes(want)), (key, values)


def test_input_values_are_the_raw_values_cantools_decodes(db, bench_db):
    """The decoder reads the raw bits itself; on random payloads every signal it uses has the raw value cantools
    decodes, little- and big-endian, signed and unsigned; float and multiplexed messages are left to cantools."""
    from online_id.io.dbc import _RawReader

    rng = np.random.default_rng(12)
    for dbx, mapping in ((db, RoleMapping()), (bench_db, BENCH_MAPPING)):
        dec = InputDecoder(dbx, mapping)
        for (fid, _ext), plan in dec._plans.items():
            msg = dbx.get_message_by_frame_id(fid)
            assert isinstance(plan.decode, _RawReader)
            for _ in range(500):
                data = bytes(rng.integers(0, 256, plan.length, dtype=np.uint8))
                want = msg.decode(data, decode_choices=False, scaling=False)
                got = plan.decode(data)
                assert got == {k: want[k] for k in got} and len(got) >= 1
    float_torque = RoleMapping(dyno_speed=BENCH_MAPPING.dyno_speed, engine_speed=BENCH_MAPPING.engine_speed,
                               dyno_torque=RoleSignal("FloatTorque", "TorqueF", "Nm", 1), command=None)
    paged = RoleMapping(dyno_speed=RoleSignal("Paged", "PagedSpeed", "rpm", 1),
                        engine_speed=BENCH_MAPPING.engine_speed, dyno_torque=BENCH_MAPPING.dyno_torque, command=None)
    for mapping, name in ((float_torque, "FloatTorque"), (paged, "Paged")):
        dec = InputDecoder(bench_db, mapping)
        plan = dec._plans[(int(bench_db.get_message_by_name(name).frame_id), False)]
        assert not isinstance(plan.decode, _RawReader)
