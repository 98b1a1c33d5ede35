"""Wire protocol: framing primitives, codec round trips, every malformed class, stream resync."""

from __future__ import annotations

import contextlib
import math
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dvt_driver.errors import DvtDriverError, ProtocolError
from dvt_driver.link.protocol import (
    COUNT_MAX,
    COUNT_MIN,
    FIRMWARE_ID_MAX_LEN,
    MAX_FRAME_LEN,
    PROTOCOL_VERSION,
    SAMPLE_V2_WIRE_LEN,
    SAMPLE_WIRE_LEN,
    Ack,
    Command,
    Config,
    FrameDecoder,
    FrameType,
    Hello,
    HelloAck,
    Message,
    Mode,
    Nack,
    NackReason,
    Sample,
    SequenceTracker,
    SequenceUpdate,
    Status,
    cobs_decode,
    cobs_encode,
    crc16,
    decode_frame,
    encode,
    max_sample_rate,
    pack_frame,
    sample_wire_len,
    unwrap_count,
    wrap_count,
)

# ------------------------------------------------------------------------------------------
# strategies

f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
u16 = st.integers(0, 2**16 - 1)
u32 = st.integers(0, 2**32 - 1)
i32 = st.integers(-(2**31), 2**31 - 1)
f32x3 = st.tuples(f32, f32, f32)
printable = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E),
                    max_size=FIRMWARE_ID_MAX_LEN)
request_type = st.sampled_from([FrameType.HELLO, FrameType.COMMAND, FrameType.CONFIG])

messages: st.SearchStrategy[Message] = st.one_of(
    st.builds(Hello, u16),
    st.builds(HelloAck, st.integers(0, 1), u32, u32, printable),
    st.builds(HelloAck, st.integers(2, 2**16 - 1), u32, u32, printable, u32, u32),
    st.builds(Sample, u32, st.integers(0, 2**64 - 1), f32, f32, f32, f32x3,
              st.integers(0, 0xFF).map(Status)),
    st.builds(Sample, u32, st.integers(0, 2**64 - 1), f32, f32, f32, f32x3,
              st.integers(0, 0xFF).map(Status), st.tuples(i32, i32)),
    st.builds(Command, u16, st.sampled_from(list(Mode)), f32, f32x3),
    st.builds(Config, u16, u32),
    st.builds(Ack, request_type, u16),
    st.builds(Nack, request_type, u16, st.sampled_from(list(NackReason))),
)


def sample(seq: int, t_us: int | None = None) -> Sample:
    return Sample(seq, 1000 * seq + 17 if t_us is None else t_us, 0.5 * seq, -0.25, 1.5,
                  (0.0, 0.75, 2.0), Status.ENABLED | Status.BRAKE1)


EXAMPLES: list[Message] = [
    Hello(),
    Hello(7),
    HelloAck(PROTOCOL_VERSION, 1000, 100_000, "dvt-plant 0.1.0"),
    HelloAck(1, 500, 0, ""),
    HelloAck(1, 500, 0, "x" * FIRMWARE_ID_MAX_LEN),
    sample(0),
    Sample(2**32 - 1, 2**64 - 1, -3.5, 2.0**100, -0.0, (1.0, 2.0, 3.0), Status(0xFF)),
    Command(0, Mode.OFF, 0.0, (0.0, 0.0, 0.0)),
    Command(65535, Mode.CURRENT, -2.5, (0.5, 0.0, 1.25)),
    Command(12, Mode.SPEED, 150.0, (0.0, 1.0, 0.0)),
    Config(3, 1000),
    Config(65535, 2**32 - 1),
    Ack(FrameType.COMMAND, 12),
    Ack(FrameType.HELLO, 0),
    Nack(FrameType.CONFIG, 3, NackReason.INVALID_VALUE),
    Nack(FrameType.HELLO, 0, NackReason.UNSUPPORTED_VERSION),
]


# ------------------------------------------------------------------------------------------
# primitives


def test_crc16_ccitt_false_check_value() -> None:
    assert crc16(b"123456789") == 0x29B1
    assert crc16(b"") == 0xFFFF


@pytest.mark.parametrize(("raw", "encoded"), [
    (b"", b"\x01"),
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
])
def test_cobs_reference_vectors(raw: bytes, encoded: bytes) -> None:
    # the Wikipedia "Consistent Overhead Byte Stuffing" examples (without the delimiter)
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


@given(st.binary(max_size=1200))
def test_cobs_round_trip_has_no_zero_and_bounded_overhead(raw: bytes) -> None:
    enc = cobs_encode(raw)
    assert 0 not in enc
    assert len(enc) <= len(raw) + 1 + len(raw) // 254
    assert cobs_decode(enc) == raw


# ------------------------------------------------------------------------------------------
# codec round trips and sizes


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip_examples(msg: Message) -> None:
    frame = encode(msg)
    assert frame.endswith(b"\x00")
    assert 0 not in frame[:-1]
    assert decode_frame(frame) == msg
    assert decode_frame(frame[:-1]) == msg  # delimiter optional for decode_frame
    assert type(decode_frame(frame)) is type(msg)


@given(messages)
def test_round_trip_property(msg: Message) -> None:
    frame = encode(msg)
    assert len(frame) <= MAX_FRAME_LEN
    assert decode_frame(frame) == msg


def test_decoded_types_are_enums() -> None:
    s = decode_frame(encode(sample(1)))
    assert isinstance(s, Sample)
    assert isinstance(s.status, Status)
    assert Status.BRAKE1 in s.status and Status.FAULT not in s.status
    c = decode_frame(encode(Command(1, Mode.SPEED, 1.0, (0.0, 0.0, 0.0))))
    assert isinstance(c, Command) and c.mode is Mode.SPEED
    n = decode_frame(encode(Nack(FrameType.COMMAND, 1, NackReason.FAULT_LATCHED)))
    assert isinstance(n, Nack)
    assert n.ref_type is FrameType.COMMAND and n.reason is NackReason.FAULT_LATCHED


def test_float32_rounding_is_the_only_change() -> None:
    msg = Command(1, Mode.CURRENT, 0.1, (0.8, 0.0, 1 / 3))
    out = decode_frame(encode(msg))
    assert isinstance(out, Command)
    f32r = struct.Struct("<f")
    assert out.setpoint == f32r.unpack(f32r.pack(0.1))[0]
    assert out.setpoint == pytest.approx(0.1, rel=1e-7)
    assert out.brake_currents[2] == pytest.approx(1 / 3, rel=1e-7)


# golden vectors: the worked examples of docs/protocol.md, section 8; any change here is a
# wire-format change and needs a PROTOCOL_VERSION bump
GOLDEN: list[tuple[Message, str]] = [
    (Hello(1), "03 01 01 03 9D C8 00"),
    (Hello(2), "03 01 02 03 CE 9D 00"),
    (HelloAck(2, 1000, 200_000, "dvt-plant 0.2", 4096, 16384),
     "03 02 02 03 E8 03 01 04 40 0D 03 01 02 10 01 01 02 40 01 11 0D 64 76 74 2D 70 6C 61 6E "
     "74 20 30 2E 32 ED C9 00"),
    (Sample(1, 2000, 10.0, -2.5, 1.25, (0.0, 0.5, 0.0), Status.ENABLED | Status.BRAKE2,
            (4096, -16384)),
     "03 11 01 01 01 03 D0 07 01 01 01 01 01 01 01 03 20 41 01 03 20 C0 01 03 A0 3F "
     "01 01 01 01 01 01 02 3F 01 01 01 02 21 01 02 10 01 01 06 C0 FF FF D5 02 00"),
    (HelloAck(1, 1000, 100_000, "dvt-plant 0.1"),
     "03 02 01 03 E8 03 01 04 A0 86 01 11 0D 64 76 74 2D 70 6C 61 6E 74 20 30 2E 31 C3 6A 00"),
    (Sample(1, 2000, 10.0, -2.5, 1.25, (0.0, 0.5, 0.0), Status.ENABLED | Status.BRAKE2),
     "03 10 01 01 01 03 D0 07 01 01 01 01 01 01 01 03 20 41 01 03 20 C0 01 03 A0 3F "
     "01 01 01 01 01 01 02 3F 01 01 01 02 21 03 C6 F9 00"),
    (Command(7, Mode.SPEED, 50.0, (0.0, 0.0, 0.75)),
     "03 20 07 02 02 01 03 48 42 01 01 01 01 01 01 01 01 01 05 40 3F 77 E1 00"),
    (Config(8, 1000), "03 21 08 03 E8 03 01 03 62 72 00"),
    (Ack(FrameType.COMMAND, 7), "04 30 20 07 03 78 B7 00"),
    (Nack(FrameType.CONFIG, 8, NackReason.INVALID_VALUE), "04 31 21 08 04 02 AA 7F 00"),
]


@pytest.mark.parametrize(("msg", "wire"), GOLDEN, ids=lambda x: type(x).__name__)
def test_golden_vectors(msg: Message, wire: str) -> None:
    assert encode(msg) == bytes.fromhex(wire)
    assert decode_frame(bytes.fromhex(wire)) == msg


@pytest.mark.parametrize(("msg", "length"), [
    (Hello(), 7), (HelloAck(1, 1000, 0, "abc"), 19), (sample(5), 43),
    (HelloAck(2, 1000, 0, "abc", 4096, 16384), 27),
    (Sample(5, 5000, 1.0, 0.5, 0.0, (0.0, 0.0, 0.0), Status(0), (-1, 2**31 - 1)), 51),
    (Command(1, Mode.OFF, 0.0, (0.0, 0.0, 0.0)), 24), (Config(1, 1000), 11),
    (Ack(FrameType.CONFIG, 1), 8), (Nack(FrameType.CONFIG, 1, NackReason.NOT_READY), 9),
])
def test_wire_lengths_match_the_document(msg: Message, length: int) -> None:
    assert len(encode(msg)) == length


def test_sample_budget_fits_921600_baud() -> None:
    assert SAMPLE_WIRE_LEN == 43
    assert max_sample_rate(921600) == pytest.approx(921600 / 430)
    assert max_sample_rate(921600) > 2000  # 1 kHz uses < 50 % of the line
    assert max_sample_rate(115200) < 1000  # ... while 115200 baud could not carry 1 kHz
    assert max_sample_rate(921600, bits_per_byte=11) == pytest.approx(921600 / 473)
    for bad in (0, -9600, 1.5, True):
        with pytest.raises(ProtocolError, match="baud"):
            max_sample_rate(bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------
# malformed frames: one test per class, each checks the reason


def reason_of(frame: bytes) -> str:
    with pytest.raises(ProtocolError) as info:
        decode_frame(frame)
    assert isinstance(info.value, DvtDriverError)
    return info.value.reason


def body_of(msg: Message) -> bytes:
    """type + body of a valid message (no CRC, no COBS)."""
    return cobs_decode(encode(msg)[:-1])[:-2]


def test_protocol_error_is_a_driver_error_and_value_error() -> None:
    assert issubclass(ProtocolError, DvtDriverError)
    assert issubclass(ProtocolError, ValueError)


def test_empty_frame() -> None:
    assert reason_of(b"") == "empty"
    assert reason_of(b"\x00") == "empty"


def test_oversize_frame() -> None:
    assert reason_of(b"\x05" * (MAX_FRAME_LEN + 1)) == "oversize"


def test_bad_crc() -> None:
    payload = body_of(sample(3))
    good = crc16(payload)
    frame = cobs_encode(payload + struct.pack("<H", good ^ 0x0001)) + b"\x00"
    assert reason_of(frame) == "crc"
    with pytest.raises(ProtocolError, match=r"CRC mismatch: frame carries 0x[0-9A-F]{4}"):
        decode_frame(frame)


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_every_single_bit_flip_is_detected(msg: Message) -> None:
    frame = encode(msg)[:-1]
    for i in range(len(frame)):
        for bit in range(8):
            corrupted = bytearray(frame)
            corrupted[i] ^= 1 << bit
            with pytest.raises(ProtocolError):
                decode_frame(bytes(corrupted))


def test_truncated_frames() -> None:
    assert reason_of(pack_frame(b"")) == "truncated"  # CRC only
    assert reason_of(cobs_encode(b"\x10\x01")) == "truncated"
    frame = encode(sample(9))[:-1]
    for cut in range(1, len(frame)):
        with pytest.raises(ProtocolError) as info:
            decode_frame(frame[:cut])
        assert info.value.reason in {"cobs", "truncated", "crc", "length"}


def test_unknown_type() -> None:
    assert reason_of(pack_frame(b"\x7f\x01\x02")) == "unknown_type"
    assert reason_of(pack_frame(b"\x00")) == "unknown_type"


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_wrong_length_for_the_type(msg: Message) -> None:
    payload = body_of(msg)
    assert reason_of(pack_frame(payload + b"\x01")) == "length"
    if len(payload) > 1:
        assert reason_of(pack_frame(payload[:-1])) == "length"


def test_wrong_length_message_names_type_and_sizes() -> None:
    with pytest.raises(ProtocolError, match="SAMPLE frame: body of 37 bytes, expected 38"):
        decode_frame(pack_frame(body_of(sample(1))[:-1]))


def test_cobs_errors() -> None:
    assert reason_of(b"\x05\x01\x02") == "cobs"  # block runs past the end
    assert reason_of(b"\x02\x00\x01\x01") == "cobs"  # 0x00 code byte inside the frame
    assert reason_of(b"\x03\x01\x00") == "cobs"  # trailing 0x00 is taken as the delimiter
    assert reason_of(b"\x04\x01\x00\x01") == "cobs"  # 0x00 inside a block


def _sample_payload(**over: object) -> bytes:
    fields: dict[str, object] = {"seq": 1, "t": 2, "sun": 0.0, "car": 0.0, "cur": 0.0,
                                 "b1": 0.0, "b2": 0.0, "b3": 0.0, "status": 0}
    fields.update(over)
    return bytes([FrameType.SAMPLE]) + struct.pack("<IQffffffH", *fields.values())


@pytest.mark.parametrize("field", ["sun", "car", "cur", "b1", "b2", "b3"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_floats_in_a_sample_are_refused(field: str, bad: float) -> None:
    assert reason_of(pack_frame(_sample_payload(**{field: bad}))) == "value"


def test_bad_field_values_are_refused() -> None:
    assert reason_of(pack_frame(_sample_payload(status=0x0100))) == "value"
    cmd = bytes([FrameType.COMMAND]) + struct.pack("<HBffff", 1, 9, 0, 0, 0, 0)
    assert reason_of(pack_frame(cmd)) == "value"  # unknown mode
    cmd = bytes([FrameType.COMMAND]) + struct.pack("<HBffff", 1, 1, math.nan, 0, 0, 0)
    assert reason_of(pack_frame(cmd)) == "value"
    ack = bytes([FrameType.ACK]) + struct.pack("<BH", FrameType.SAMPLE, 1)
    assert reason_of(pack_frame(ack)) == "value"  # only requests are acknowledged
    nack = bytes([FrameType.NACK]) + struct.pack("<BHB", FrameType.CONFIG, 1, 0)
    assert reason_of(pack_frame(nack)) == "value"  # reason 0 is not defined
    head = bytes([FrameType.HELLO_ACK]) + struct.pack("<HIIB", 1, 1000, 0, 3)
    assert reason_of(pack_frame(head + b"a\x07c")) == "value"  # not printable
    head = bytes([FrameType.HELLO_ACK]) + struct.pack("<HIIB", 1, 1000, 0, 33)
    assert reason_of(pack_frame(head + b"a" * 33)) == "value"  # too long


# ------------------------------------------------------------------------------------------
# encode validation


@pytest.mark.parametrize(("msg", "match"), [
    (Command(1, Mode.CURRENT, math.nan, (0.0, 0.0, 0.0)), r"Command.setpoint: must be finite"),
    (Command(1, Mode.SPEED, math.inf, (0.0, 0.0, 0.0)), r"Command.setpoint: must be finite"),
    (Command(1, Mode.OFF, 0.0, (0.0, -math.inf, 0.0)), r"Command.brake_currents\[1\]"),
    (Command(1, Mode.OFF, 1e39, (0.0, 0.0, 0.0)), r"outside the float32 range"),
    (Command(1, Mode.OFF, 0.0, (0.0, 0.0)), r"brake_currents: expected 3 floats, got 2"),  # type: ignore[arg-type]
    (Command(1, 7, 0.0, (0.0, 0.0, 0.0)), r"Command.mode: unknown Mode code 7"),  # type: ignore[arg-type]
    (Command(-1, Mode.OFF, 0.0, (0.0, 0.0, 0.0)), r"Command.seq: expected 0..65535"),
    (Command(65536, Mode.OFF, 0.0, (0.0, 0.0, 0.0)), r"Command.seq: expected 0..65535"),
    (Command(True, Mode.OFF, 0.0, (0.0, 0.0, 0.0)), r"Command.seq: expected an integer"),
    (Command(1.0, Mode.OFF, 0.0, (0.0, 0.0, 0.0)), r"Command.seq: expected an integer"),  # type: ignore[arg-type]
    (Command(1, Mode.OFF, "1", (0.0, 0.0, 0.0)), r"Command.setpoint: expected a float"),  # type: ignore[arg-type]
    (Sample(1, -1, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0)), r"Sample.t_us"),
    (Sample(2**32, 0, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0)), r"Sample.seq"),
    (Sample(1, 0, math.nan, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0)), r"Sample.sun_speed"),
    (Sample(1, 0, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0x100)), r"reserved status bits"),
    (HelloAck(1, 1000, 0, "x" * 33), r"HelloAck.firmware_id"),
    (HelloAck(1, 1000, 0, "µC"), r"HelloAck.firmware_id"),
    (Config(1, 2**32), r"Config.sample_period_us"),
    (Ack(FrameType.SAMPLE, 1), r"Ack.ref_type: SAMPLE not allowed here"),
    (Nack(FrameType.COMMAND, 1, 0), r"Nack.reason: unknown NackReason code 0"),  # type: ignore[arg-type]
])
def test_encode_refuses_unencodable_fields(msg: Message, match: str) -> None:
    with pytest.raises(ProtocolError, match=match) as info:
        encode(msg)
    assert info.value.reason == "value"


def test_encode_refuses_non_messages() -> None:
    for obj in (None, b"\x01", 3, {"seq": 1}):
        with pytest.raises(ProtocolError, match="expected a protocol message") as info:
            encode(obj)  # type: ignore[arg-type]
        assert info.value.reason == "type"


def test_encode_accepts_numpy_scalars() -> None:
    np = pytest.importorskip("numpy")
    msg = Command(np.int64(4), Mode.CURRENT, np.float32(1.5), tuple(np.array([0.0, 0.5, 1.0])))
    out = decode_frame(encode(msg))
    assert out == Command(4, Mode.CURRENT, 1.5, (0.0, 0.5, 1.0))


# ------------------------------------------------------------------------------------------
# fuzz: decode_frame raises ProtocolError and nothing else


@settings(max_examples=2000, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_decode_frame_fuzz_raises_only_protocol_error(data: bytes) -> None:
    try:
        msg = decode_frame(data)
    except ProtocolError as err:
        assert err.reason in {"empty", "oversize", "cobs", "truncated", "crc", "unknown_type",
                              "length", "value"}
    else:
        assert decode_frame(encode(msg)) == msg


@settings(max_examples=1000)
@given(messages, st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)),
                          min_size=1, max_size=4))
def test_decode_frame_fuzz_mutated_valid_frames(msg: Message, edits: list[tuple[int, int]]) -> None:
    frame = bytearray(encode(msg)[:-1])
    for pos, value in edits:
        frame[pos % len(frame)] = value
    with contextlib.suppress(ProtocolError):  # anything else fails the test
        decode_frame(bytes(frame))


# ------------------------------------------------------------------------------------------
# stream decoder


def stream_of(msgs: list[Message]) -> bytes:
    return b"".join(encode(m) for m in msgs)


def test_stream_decoder_in_arbitrary_chunks() -> None:
    msgs = [sample(i) for i in range(50)] + EXAMPLES
    data = stream_of(msgs)
    for chunk in (1, 2, 7, 43, 1000):
        dec = FrameDecoder()
        out: list[Message] = []
        for i in range(0, len(data), chunk):
            out += dec.feed(data[i:i + chunk])
        assert out == msgs
        assert (dec.frames_good, dec.frames_bad, dec.bytes_discarded) == (len(msgs), 0, 0)
        assert dec.pending == 0


def test_stream_ignores_empty_frames() -> None:
    dec = FrameDecoder()
    out = dec.feed(b"\x00\x00" + encode(Hello()) + b"\x00\x00\x00" + encode(Hello(2)))
    assert out == [Hello(), Hello(2)]
    assert dec.frames_bad == 0 and dec.bytes_discarded == 0


def test_stream_resyncs_after_garbage() -> None:
    garbage = b"\xde\xad\xbe\xef\x00\x13\x37\xff\x01\x00"
    dec = FrameDecoder()
    out = dec.feed(encode(sample(1)) + garbage + encode(sample(2)) + encode(sample(3)))
    assert out == [sample(1), sample(2), sample(3)]
    assert dec.frames_bad == 2  # two garbage fragments, each ended by a 0x00
    assert dec.bytes_discarded == len(garbage) - 2
    assert dec.last_error is not None


def test_stream_garbage_without_delimiter_costs_one_frame() -> None:
    dec = FrameDecoder()
    out = dec.feed(encode(sample(1)) + b"\x55\x66\x77" + encode(sample(2)) + encode(sample(3)))
    assert out == [sample(1), sample(3)]
    assert dec.frames_bad == 1


@pytest.mark.parametrize("victim", [0, 5, 20, 42])
def test_stream_lost_byte_costs_one_frame(victim: int) -> None:
    frames = [encode(sample(i)) for i in range(6)]
    lost = bytearray(frames[2])
    del lost[victim]
    dec = FrameDecoder()
    out = dec.feed(b"".join(frames[:2]) + bytes(lost) + b"".join(frames[3:]))
    if victim == len(frames[2]) - 1:  # the delimiter was lost: frames 2 and 3 merge
        assert out == [sample(i) for i in (0, 1, 4, 5)]
    else:
        assert out == [sample(i) for i in (0, 1, 3, 4, 5)]
    assert dec.frames_bad == 1


def test_stream_crc_errors_are_counted() -> None:
    payload = body_of(sample(7))
    bad = cobs_encode(payload + struct.pack("<H", crc16(payload) ^ 0xFFFF)) + b"\x00"
    dec = FrameDecoder()
    assert dec.feed(bad + encode(sample(8))) == [sample(8)]
    assert (dec.frames_bad, dec.crc_errors) == (1, 1)
    assert dec.errors_by_reason == {"crc": 1}


def test_stream_bounds_its_buffer_and_drops_oversize_frames() -> None:
    dec = FrameDecoder(max_frame_len=64)
    huge = b"\x07" * 10_000
    out: list[Message] = []
    for i in range(0, len(huge), 100):
        out += dec.feed(huge[i:i + 100])
        assert dec.pending <= 64
    out += dec.feed(b"\x00" + encode(sample(1)))
    assert out == [sample(1)]
    assert dec.frames_bad == 1 and dec.errors_by_reason == {"oversize": 1}
    assert dec.bytes_discarded == len(huge)


def test_unsynced_start_discards_the_first_fragment_without_counting_a_bad_frame() -> None:
    first = encode(sample(1))
    dec = FrameDecoder(synced=False)
    out = dec.feed(first[10:] + encode(sample(2)) + b"\x99\x00")
    assert out == [sample(2)]
    assert dec.frames_bad == 1  # the trailing garbage, seen after synchronisation
    assert dec.bytes_discarded == (len(first) - 10 - 1) + 1  # fragment + garbage byte


def test_unsynced_start_keeps_a_first_fragment_that_is_a_whole_frame() -> None:
    dec = FrameDecoder(synced=False)
    assert dec.feed(encode(sample(1)) + encode(sample(2))) == [sample(1), sample(2)]
    assert dec.frames_bad == 0


def test_reset_discards_the_partial_frame_and_keeps_counters() -> None:
    dec = FrameDecoder()
    frame = encode(sample(1))
    assert dec.feed(frame + frame[:20]) == [sample(1)]
    dec.reset()
    assert dec.pending == 0 and dec.bytes_discarded == 20 and dec.frames_good == 1
    assert dec.feed(frame[20:] + frame) == [sample(1)]  # tail of the old frame: unsynced
    assert dec.frames_bad == 0 and dec.frames_good == 2


def test_frame_decoder_rejects_bad_limit() -> None:
    with pytest.raises(ProtocolError, match="max_frame_len"):
        FrameDecoder(0)


@settings(max_examples=500, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=2000), st.integers(1, 64))
def test_feed_never_raises_on_arbitrary_bytes(data: bytes, chunk: int) -> None:
    dec = FrameDecoder()
    n = 0
    for i in range(0, len(data), chunk):
        n += len(dec.feed(data[i:i + chunk]))
    assert dec.frames_good == n
    assert dec.pending <= dec.max_frame_len


@settings(max_examples=500, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(messages, max_size=5), st.binary(max_size=400), st.lists(messages, max_size=5),
       st.booleans(), st.integers(1, 50))
def test_feed_recovers_good_frames_around_garbage(
        before: list[Message], garbage: bytes, after: list[Message], terminate: bool, chunk: int) -> None:
    data = stream_of(before) + garbage + (b"\x00" if terminate else b"") + stream_of(after)
    dec = FrameDecoder()
    out: list[Message] = []
    for i in range(0, len(data), chunk):
        out += dec.feed(data[i:i + chunk])
    # every frame before the garbage survives, and every frame after it except, when the
    # garbage has no trailing delimiter, the first one (merged with the garbage tail)
    assert out[:len(before)] == before
    tail = after if terminate else after[1:]
    assert out[len(out) - len(tail):] == tail


# ------------------------------------------------------------------------------------------
# sequence tracker


def test_sequence_tracker_counts_gaps() -> None:
    tr = SequenceTracker()
    assert tr.update(10, 10_000) == SequenceUpdate()
    assert tr.update(11, 11_000) == SequenceUpdate()
    assert tr.update(14, 14_000) == SequenceUpdate(lost=2)
    assert (tr.samples, tr.lost, tr.resets, tr.duplicates) == (3, 2, 0, 0)


def test_sequence_tracker_handles_u32_wrap() -> None:
    tr = SequenceTracker()
    tr.update(2**32 - 2, 5_000_000)
    assert tr.update(2**32 - 1, 5_001_000) == SequenceUpdate()
    assert tr.update(0, 5_002_000) == SequenceUpdate()
    assert tr.update(3, 5_005_000) == SequenceUpdate(lost=2)
    assert tr.resets == 0


def test_sequence_tracker_detects_resets() -> None:
    tr = SequenceTracker()
    tr.update(500, 500_000)
    assert tr.update(0, 1_000) == SequenceUpdate(reset=True)  # sequence went back
    assert tr.update(1, 2_000) == SequenceUpdate()
    tr2 = SequenceTracker()
    tr2.update(2**32 - 3, 9_000_000)
    # looks like a forward step across the wrap, but the clock restarted: a reset
    assert tr2.update(0, 100) == SequenceUpdate(reset=True)
    assert tr2.update(5, 1_000) == SequenceUpdate(lost=4)
    assert (tr.resets, tr2.resets, tr2.lost) == (1, 1, 4)


def test_sequence_tracker_duplicates_and_forget() -> None:
    tr = SequenceTracker()
    tr.update(1, 1_000)
    assert tr.update(1, 1_000) == SequenceUpdate(duplicate=True)
    assert tr.update(1, 7_000) == SequenceUpdate(reset=True)  # same seq, different clock
    tr.forget()
    assert tr.update(100, 9_000) == SequenceUpdate()
    assert (tr.duplicates, tr.resets, tr.lost) == (1, 1, 0)


# ---------------------------------------------------------------------------------------------
# version 2: encoder counts


def test_version_constants() -> None:
    assert PROTOCOL_VERSION == 2
    assert Hello().protocol_version == 2
    assert SAMPLE_V2_WIRE_LEN == 51
    assert sample_wire_len(1) == 43 and sample_wire_len(2) == 51
    # 1 kHz of SAMPLE_V2 plus an ACK per sample still fits a 921600 baud line (64 %)
    assert max_sample_rate(921600, protocol_version=2) == pytest.approx(921600 / 510)
    assert 1000 * (51 + 8) / 92160 < 0.65
    with pytest.raises(ProtocolError, match="protocol_version"):
        sample_wire_len(3)


def test_sample_v2_round_trip_keeps_counts() -> None:
    msg = Sample(9, 9000, 1.0, -0.5, 0.25, (0.0, 0.0, 1.0), Status.BRAKE3,
                 (-(2**31), 2**31 - 1))
    frame = encode(msg)
    assert frame[1] == FrameType.SAMPLE_V2
    assert decode_frame(frame) == msg
    assert decode_frame(encode(sample(3))).counts is None  # version 1 layout unchanged


def test_hello_ack_v2_counts_per_rev_round_trip_and_v1_refuses_them() -> None:
    ack = HelloAck(2, 1000, 0, "x", 4096, 16384)
    assert decode_frame(encode(ack)) == ack
    with pytest.raises(ProtocolError, match="sun_counts_per_rev|version >= 2"):
        encode(HelloAck(1, 1000, 0, "x", 4096, 0))
    # a future version keeps the version-2 head
    assert decode_frame(encode(HelloAck(3, 1000, 0, "", 1, 2))) == HelloAck(3, 1000, 0, "", 1, 2)


@pytest.mark.parametrize("counts", [(2**31, 0), (0, -(2**31) - 1), (1.5, 0), (True, 0), (1,),
                                    (1, 2, 3), "ab", 7])
def test_sample_counts_refused_when_not_i32(counts: object) -> None:
    with pytest.raises(ProtocolError, match="Sample.counts"):
        encode(Sample(1, 1, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0), counts))  # type: ignore[arg-type]


def test_sample_v2_wrong_lengths_are_malformed() -> None:
    payload = bytes(encode(Sample(1, 1, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), Status(0), (1, 2))))
    body = cobs_decode(payload[:-1])[:-2]
    assert reason_of(pack_frame(body[:-1])) == "length"
    assert reason_of(pack_frame(body + b"\x01")) == "length"
    # a version-1 body under the version-2 type and vice versa
    v1 = cobs_decode(encode(sample(1))[:-1])[:-2]
    assert reason_of(pack_frame(bytes([FrameType.SAMPLE_V2]) + v1[1:])) == "length"
    assert reason_of(pack_frame(bytes([FrameType.SAMPLE]) + body[1:])) == "length"
    # a version-2 HELLO_ACK cut inside its head
    ack = cobs_decode(encode(HelloAck(2, 1000, 0, "", 1, 1))[:-1])[:-2]
    assert reason_of(pack_frame(ack[:12])) == "length"


@given(st.integers(-(2**40), 2**40), st.integers(-(2**31) + 1, 2**31 - 1))
def test_unwrap_count_follows_any_step_below_2_pow_31(start: int, step: int) -> None:
    raw0 = wrap_count(start)
    assert COUNT_MIN <= raw0 <= COUNT_MAX
    assert unwrap_count(start, wrap_count(start + step)) == start + step
