"""Binary wire protocol between the host and the DVT motor/brake controller (pure, no I/O).

Every frame on the line is ``COBS(type + body + CRC16) + 0x00``:

* ``type`` (u8) is a :class:`FrameType`; ``body`` is a fixed little-endian ``struct`` layout
  per type (HELLO_ACK ends in a length-prefixed ASCII string);
* the CRC is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR) of
  ``type + body``, stored little-endian;
* COBS removes every 0x00 from the frame, so 0x00 only ever appears as the frame delimiter and
  a receiver resynchronises at the next delimiter after garbage or a lost byte.

The byte-exact specification, the session rules (hello and version negotiation, watchdog,
acknowledgements) and the line budget (1 kHz samples use 47 % (version 1) or 55 % (version 2,
with encoder counts) of a 921600 baud 8N1 line) are in ``docs/protocol.md``.

Versions: this module speaks versions :data:`MIN_PROTOCOL_VERSION` (1) to
:data:`PROTOCOL_VERSION` (2). Version 2 adds the encoder counts: a SAMPLE_V2 frame (0x11,
:class:`Sample` with ``counts``) and the encoders' counts per revolution in HELLO_ACK. The
decoder is stateless: a SAMPLE's layout is given by its type byte, a HELLO_ACK's by its own
``protocol_version`` field.

Public API:

* message dataclasses (frozen): :class:`Hello`, :class:`HelloAck`, :class:`Sample`,
  :class:`Command`, :class:`Config`, :class:`Ack`, :class:`Nack`; ``Message`` is their union;
* :func:`encode` (message -> complete frame with delimiter) and :func:`decode_frame`
  (one frame -> message); both raise :class:`~dvt_driver.errors.ProtocolError` and nothing else;
* :class:`FrameDecoder`: streaming decoder that never raises on garbage and counts what it drops;
* :class:`SequenceTracker`: lost samples and controller resets from sequence numbers and clock;
* :func:`max_sample_rate`: samples per second a line of a given baud rate can carry.
"""

from __future__ import annotations

import binascii
import math
import numbers
import operator
import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import Any, TypeAlias

from dvt_driver.errors import ProtocolError

__all__ = [
    "COUNT_MAX",
    "COUNT_MIN",
    "DEFAULT_BAUD",
    "FIRMWARE_ID_MAX_LEN",
    "MAX_FRAME_LEN",
    "MIN_PROTOCOL_VERSION",
    "PROTOCOL_VERSION",
    "SAMPLE_V2_WIRE_LEN",
    "SAMPLE_WIRE_LEN",
    "SUPPORTED_VERSIONS",
    "Ack",
    "Command",
    "Config",
    "FrameDecoder",
    "FrameType",
    "Hello",
    "HelloAck",
    "Message",
    "Mode",
    "Nack",
    "NackReason",
    "Sample",
    "SequenceTracker",
    "SequenceUpdate",
    "Status",
    "cobs_decode",
    "cobs_encode",
    "crc16",
    "decode_frame",
    "encode",
    "max_sample_rate",
    "pack_frame",
    "sample_wire_len",
    "unwrap_count",
    "wrap_count",
]

PROTOCOL_VERSION = 2
"""Newest version of this protocol (the host offers it in HELLO); version 2 adds the encoder
counts (SAMPLE_V2, counts per revolution in HELLO_ACK)."""

MIN_PROTOCOL_VERSION = 1
"""Oldest version this implementation still speaks (speeds only, no encoder counts)."""

SUPPORTED_VERSIONS: tuple[int, ...] = (1, 2)
"""Every version this implementation speaks, oldest first."""

COUNT_MIN = -(1 << 31)
COUNT_MAX = (1 << 31) - 1
"""Range of an encoder count on the wire (i32, two's complement; wraps modulo 2**32)."""

DEFAULT_BAUD = 921600
"""Nominal line rate [bit/s] (8N1: 10 bits per byte, 92160 bytes/s)."""

MAX_FRAME_LEN = 256
"""Longest COBS-encoded frame (bytes between delimiters) a receiver accepts; longer is
discarded as ``oversize``. The longest defined frame (a version-2 HELLO_ACK with a 32-character
firmware id) is 55 bytes."""

FIRMWARE_ID_MAX_LEN = 32
"""Longest firmware id string in HELLO_ACK [characters, printable ASCII]."""

DELIMITER = 0x00

_F32_MAX = 3.4028234663852886e38
_U16 = 16
_U32 = 32
_U64 = 64


class FrameType(IntEnum):
    """Frame type byte (first byte of the decoded payload)."""

    HELLO = 0x01  #: host -> device: protocol version
    HELLO_ACK = 0x02  #: device -> host: version, sample period, watchdog timeout, firmware id
    SAMPLE = 0x10  #: device -> host: one controller sample (speeds, currents, status)
    SAMPLE_V2 = 0x11  #: device -> host: SAMPLE plus the two encoder counts (version 2)
    COMMAND = 0x20  #: host -> device: mode, set-point, brake currents
    CONFIG = 0x21  #: host -> device: sample period
    ACK = 0x30  #: device -> host: a HELLO/COMMAND/CONFIG was accepted
    NACK = 0x31  #: device -> host: a HELLO/COMMAND/CONFIG was refused, with a reason


class Mode(IntEnum):
    """Drive-motor control mode of a COMMAND."""

    OFF = 0  #: motor current forced to zero (set-point ignored); clears a latched fault
    CURRENT = 1  #: set-point is the drive-motor current [A]
    SPEED = 2  #: set-point is the sun-shaft speed [rad/s] (device's speed loop)


class Status(IntFlag):
    """Status bits of a SAMPLE (u16; bits 8..15 are reserved and must be zero)."""

    ENABLED = 1 << 0  #: motor power stage enabled (mode CURRENT or SPEED active)
    WATCHDOG = 1 << 1  #: command watchdog expired; motor off until the next accepted COMMAND
    OVERSPEED = 1 << 2  #: device's own overspeed trip fired (latches FAULT)
    CURRENT_LIMIT = 1 << 3  #: device is limiting the motor current this sample
    BRAKE1 = 1 << 4  #: band brake 1 engaged
    BRAKE2 = 1 << 5  #: band brake 2 engaged
    BRAKE3 = 1 << 6  #: band brake 3 engaged
    FAULT = 1 << 7  #: fault latched: motor off, brakes hold, until a COMMAND with mode OFF


_STATUS_MASK = 0xFF


class NackReason(IntEnum):
    """Why the device refused a HELLO, COMMAND or CONFIG."""

    UNSUPPORTED_VERSION = 1  #: HELLO with a protocol version the device does not speak
    INVALID_VALUE = 2  #: a field is outside what the device accepts (e.g. sample period)
    NOT_READY = 3  #: COMMAND or CONFIG before a successful HELLO
    FAULT_LATCHED = 4  #: COMMAND with mode CURRENT/SPEED while FAULT is latched


# ---------------------------------------------------------------------------------------------
# messages


@dataclass(frozen=True, slots=True)
class Hello:
    """Host -> device: open a session speaking ``protocol_version``."""

    protocol_version: int = PROTOCOL_VERSION


@dataclass(frozen=True, slots=True)
class HelloAck:
    """Device -> host: answer to a HELLO the device accepts.

    Attributes:
        protocol_version: version the device speaks for this session (at most the HELLO's).
        sample_period_us: current sample period [µs].
        watchdog_timeout_us: the device switches the motor off when no COMMAND arrived for this
            long [µs]; 0 means the device has no command watchdog.
        firmware_id: printable ASCII, at most :data:`FIRMWARE_ID_MAX_LEN` characters.
        sun_counts_per_rev: version >= 2: counts of the sun-shaft encoder per revolution
            (u32; 0 = no sun-shaft encoder). Must be 0 in version 1 (not on the wire).
        output_counts_per_rev: version >= 2: counts of the output (carrier-3) encoder per
            revolution (u32; 0 = no output encoder). Must be 0 in version 1.
    """

    protocol_version: int
    sample_period_us: int
    watchdog_timeout_us: int
    firmware_id: str
    sun_counts_per_rev: int = 0
    output_counts_per_rev: int = 0


@dataclass(frozen=True, slots=True)
class Sample:
    """Device -> host: one controller sample.

    Attributes:
        seq: sample sequence number (u32, +1 per sample, wraps modulo 2**32).
        t_us: controller sample clock at the sample instant [µs since controller start] (u64).
        sun_speed: sun-shaft (drive-motor) speed [rad/s].
        carrier3_speed: carrier-3 (output) speed [rad/s].
        motor_current: drive-motor winding current [A].
        brake_currents: band-brake coil currents (brake1, brake2, brake3) [A].
        status: :class:`Status` bits.
        counts: version 2 only: ``(sun_counts, output_counts)``, the raw encoder counts
            (i32 each, wrapping modulo 2**32; zero at the encoder's reference, see
            ``docs/protocol.md``); ``None`` for a version-1 SAMPLE. A sample with counts is
            sent as a SAMPLE_V2 frame (0x11).
    """

    seq: int
    t_us: int
    sun_speed: float
    carrier3_speed: float
    motor_current: float
    brake_currents: tuple[float, float, float]
    status: Status
    counts: tuple[int, int] | None = None


@dataclass(frozen=True, slots=True)
class Command:
    """Host -> device: drive-motor mode and set-point, brake-coil current set-points.

    Attributes:
        seq: command sequence number (u16, wraps); echoed in the ACK/NACK.
        mode: :class:`Mode`.
        setpoint: motor current [A] in ``CURRENT``, sun-shaft speed [rad/s] in ``SPEED``,
            ignored (send 0.0) in ``OFF``.
        brake_currents: coil current set-points (brake1, brake2, brake3) [A].
    """

    seq: int
    mode: Mode
    setpoint: float
    brake_currents: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class Config:
    """Host -> device: set the sample period.

    Attributes:
        seq: request sequence number (u16, wraps; shares the counter with COMMAND);
            echoed in the ACK/NACK.
        sample_period_us: requested sample period [µs] (1000 = 1 kHz).
    """

    seq: int
    sample_period_us: int


@dataclass(frozen=True, slots=True)
class Ack:
    """Device -> host: the request ``(ref_type, ref_seq)`` was accepted and applied."""

    ref_type: FrameType
    ref_seq: int


@dataclass(frozen=True, slots=True)
class Nack:
    """Device -> host: the request ``(ref_type, ref_seq)`` was refused for ``reason``."""

    ref_type: FrameType
    ref_seq: int
    reason: NackReason


Message: TypeAlias = Hello | HelloAck | Sample | Command | Config | Ack | Nack
"""Any protocol message."""

_REQUEST_TYPES = (FrameType.HELLO, FrameType.COMMAND, FrameType.CONFIG)

# body layouts (little-endian, no padding)
_HELLO = struct.Struct("<H")
_HELLO_ACK_HEAD = struct.Struct("<HIIB")
_HELLO_ACK_HEAD_V2 = struct.Struct("<HIIIIB")
_SAMPLE = struct.Struct("<IQffffffH")
_SAMPLE_V2 = struct.Struct("<IQffffffHii")
_COMMAND = struct.Struct("<HBffff")
_CONFIG = struct.Struct("<HI")
_ACK = struct.Struct("<BH")
_NACK = struct.Struct("<BHB")
_CRC = struct.Struct("<H")

SAMPLE_WIRE_LEN = 1 + _SAMPLE.size + _CRC.size + 1 + 1
"""Bytes a version-1 SAMPLE frame occupies on the line: type + body + CRC, +1 COBS,
+1 delimiter (43)."""

SAMPLE_V2_WIRE_LEN = 1 + _SAMPLE_V2.size + _CRC.size + 1 + 1
"""Bytes a SAMPLE_V2 frame (version 2, with encoder counts) occupies on the line (51)."""


def sample_wire_len(protocol_version: int) -> int:
    """Bytes of one sample frame on the line in a session of ``protocol_version`` (43 or 51).

    Raises:
        ProtocolError: a version this implementation does not speak.
    """
    if protocol_version not in SUPPORTED_VERSIONS:
        raise ProtocolError(f"protocol_version: expected one of {list(SUPPORTED_VERSIONS)}, "
                            f"got {protocol_version!r}")
    return SAMPLE_WIRE_LEN if protocol_version == 1 else SAMPLE_V2_WIRE_LEN


def max_sample_rate(baud: int, bits_per_byte: int = 10, *, protocol_version: int = 1) -> float:
    """Most sample frames per second a line can carry [1/s].

    Args:
        baud: line rate [bit/s], > 0.
        bits_per_byte: bits per byte on the line, 10 for 8N1 (start + 8 data + stop).
        protocol_version: the session's version (1: SAMPLE of 43 bytes, 2: SAMPLE_V2 of 51).

    Returns:
        ``baud / (bits_per_byte * frame bytes)``; e.g. 2143.3 (version 1) or 1807.1
        (version 2) for 921600 baud 8N1.
    """
    for name, value in (("baud", baud), ("bits_per_byte", bits_per_byte)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ProtocolError(f"max_sample_rate: {name} must be a positive integer, "
                                f"got {value!r}")
    return baud / (bits_per_byte * sample_wire_len(protocol_version))


def wrap_count(count: int) -> int:
    """An encoder count as it goes on the wire: ``count`` modulo 2**32 as an i32."""
    return ((int(count) - COUNT_MIN) & 0xFFFFFFFF) + COUNT_MIN


def unwrap_count(previous: int, raw: int) -> int:
    """Continue an unwrapped count: ``previous`` (unwrapped) plus the wire step to ``raw``.

    The step is taken modulo 2**32 into ``[-2**31, 2**31)``, so the result is exact while
    the encoder moves less than 2**31 counts between two samples (at 4096 counts/rev: over
    500 000 revolutions).
    """
    step = ((int(raw) - int(previous)) - COUNT_MIN) & 0xFFFFFFFF
    return int(previous) + step + COUNT_MIN


# ---------------------------------------------------------------------------------------------
# framing primitives


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF; check("123456789") = 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent-overhead byte stuffing: ``data`` without any 0x00 byte (no delimiter added).

    The result is ``len(data) + 1`` bytes for ``len(data) < 254``. A run of 254 non-zero bytes
    is a 0xFF block (no implied zero); a final 0xFF block is not followed by an empty block
    (Cheshire & Baker, as in the Wikipedia examples).
    """
    out = bytearray()
    parts = bytes(data).split(b"\x00")
    last = len(parts) - 1
    for k, part in enumerate(parts):
        while len(part) >= 254:
            out.append(0xFF)
            out += part[:254]
            part = part[254:]
            if not part and k == last:
                return bytes(out)
        out.append(len(part) + 1)
        out += part
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode` (``data`` without delimiter).

    Raises:
        ProtocolError: (reason ``"cobs"``) on a 0x00 byte inside the data or a block whose
            code byte points past the end of the data.
    """
    out = bytearray()
    n = len(data)
    i = 0
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(f"COBS: 0x00 code byte at offset {i}", "cobs")
        end = i + code
        if end > n:
            raise ProtocolError(f"COBS: block at offset {i} claims {code - 1} bytes, "
                                f"only {n - i - 1} left", "cobs")
        block = data[i + 1:end]
        if 0 in block:
            raise ProtocolError(f"COBS: 0x00 byte inside block at offset {i}", "cobs")
        out += block
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def pack_frame(payload: bytes) -> bytes:
    """Complete frame from a raw payload (``type + body``): appends the CRC, COBS-encodes and
    appends the 0x00 delimiter. No check that the payload is a valid message."""
    raw = bytes(payload)
    return cobs_encode(raw + _CRC.pack(crc16(raw))) + b"\x00"


# ---------------------------------------------------------------------------------------------
# encoding


def _uint(name: str, value: Any, bits: int) -> int:
    if isinstance(value, bool):
        raise ProtocolError(f"{name}: expected an integer, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ProtocolError(f"{name}: expected an integer, got {value!r}") from None
    if not 0 <= v < (1 << bits):
        raise ProtocolError(f"{name}: expected 0..{(1 << bits) - 1} (u{bits}), got {v}")
    return v


def _f32(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ProtocolError(f"{name}: expected a float, got {value!r}")
    f = float(value)
    if not math.isfinite(f):
        raise ProtocolError(f"{name}: must be finite, got {f!r}")
    if abs(f) > _F32_MAX:
        raise ProtocolError(f"{name}: {f!r} is outside the float32 range")
    return f


def _f32x3(name: str, value: Any) -> tuple[float, float, float]:
    try:
        items = tuple(value)
    except TypeError:
        raise ProtocolError(f"{name}: expected 3 floats, got {value!r}") from None
    if len(items) != 3:
        raise ProtocolError(f"{name}: expected 3 floats, got {len(items)}")
    return (_f32(f"{name}[0]", items[0]), _f32(f"{name}[1]", items[1]),
            _f32(f"{name}[2]", items[2]))


def _enum(name: str, value: Any, enum: type[IntEnum], allowed: tuple[Any, ...] = ()) -> int:
    v = _uint(name, value, 8)
    try:
        member = enum(v)
    except ValueError:
        raise ProtocolError(f"{name}: unknown {enum.__name__} code {v}") from None
    if allowed and member not in allowed:
        raise ProtocolError(f"{name}: {member.name} not allowed here "
                            f"(expected one of {', '.join(a.name for a in allowed)})")
    return v


def _counts(name: str, value: Any) -> tuple[int, int]:
    try:
        items = tuple(value)
    except TypeError:
        raise ProtocolError(f"{name}: expected 2 integers (sun, output), got {value!r}") from None
    if len(items) != 2:
        raise ProtocolError(f"{name}: expected 2 integers (sun, output), got {len(items)}")
    out: list[int] = []
    for k, item in enumerate(items):
        if isinstance(item, bool):
            raise ProtocolError(f"{name}[{k}]: expected an integer, got {item!r}")
        try:
            v = operator.index(item)
        except TypeError:
            raise ProtocolError(f"{name}[{k}]: expected an integer, got {item!r}") from None
        if not COUNT_MIN <= v <= COUNT_MAX:
            raise ProtocolError(f"{name}[{k}]: expected {COUNT_MIN}..{COUNT_MAX} (i32; wrap it "
                                f"with wrap_count), got {v}")
        out.append(v)
    return out[0], out[1]


def _status(name: str, value: Any) -> int:
    v = _uint(name, value, _U16)
    if v & ~_STATUS_MASK:
        raise ProtocolError(f"{name}: reserved status bits set (0x{v:04X})")
    return v


def _firmware_id(name: str, value: Any) -> bytes:
    if not isinstance(value, str):
        raise ProtocolError(f"{name}: expected a str, got {value!r}")
    if len(value) > FIRMWARE_ID_MAX_LEN or not all(" " <= c <= "~" for c in value):
        raise ProtocolError(f"{name}: expected at most {FIRMWARE_ID_MAX_LEN} printable ASCII "
                            f"characters, got {value!r}")
    return value.encode("ascii")


def _encode_payload(msg: Message) -> bytes:
    if isinstance(msg, Sample):
        b = _f32x3("Sample.brake_currents", msg.brake_currents)
        head = (_uint("Sample.seq", msg.seq, _U32), _uint("Sample.t_us", msg.t_us, _U64),
                _f32("Sample.sun_speed", msg.sun_speed),
                _f32("Sample.carrier3_speed", msg.carrier3_speed),
                _f32("Sample.motor_current", msg.motor_current), *b,
                _status("Sample.status", msg.status))
        if msg.counts is None:
            return bytes([FrameType.SAMPLE]) + _SAMPLE.pack(*head)
        sun_c, out_c = _counts("Sample.counts", msg.counts)
        return bytes([FrameType.SAMPLE_V2]) + _SAMPLE_V2.pack(*head, sun_c, out_c)
    if isinstance(msg, Command):
        b = _f32x3("Command.brake_currents", msg.brake_currents)
        return bytes([FrameType.COMMAND]) + _COMMAND.pack(
            _uint("Command.seq", msg.seq, _U16), _enum("Command.mode", msg.mode, Mode),
            _f32("Command.setpoint", msg.setpoint), *b)
    if isinstance(msg, Hello):
        return bytes([FrameType.HELLO]) + _HELLO.pack(
            _uint("Hello.protocol_version", msg.protocol_version, _U16))
    if isinstance(msg, HelloAck):
        fid = _firmware_id("HelloAck.firmware_id", msg.firmware_id)
        version = _uint("HelloAck.protocol_version", msg.protocol_version, _U16)
        period = _uint("HelloAck.sample_period_us", msg.sample_period_us, _U32)
        watchdog = _uint("HelloAck.watchdog_timeout_us", msg.watchdog_timeout_us, _U32)
        sun_cpr = _uint("HelloAck.sun_counts_per_rev", msg.sun_counts_per_rev, _U32)
        out_cpr = _uint("HelloAck.output_counts_per_rev", msg.output_counts_per_rev, _U32)
        if version < 2:
            if sun_cpr or out_cpr:
                raise ProtocolError(f"HelloAck: counts per revolution ({sun_cpr}, {out_cpr}) "
                                    f"need protocol version >= 2, got version {version}")
            return bytes([FrameType.HELLO_ACK]) + _HELLO_ACK_HEAD.pack(
                version, period, watchdog, len(fid)) + fid
        return bytes([FrameType.HELLO_ACK]) + _HELLO_ACK_HEAD_V2.pack(
            version, period, watchdog, sun_cpr, out_cpr, len(fid)) + fid
    if isinstance(msg, Config):
        return bytes([FrameType.CONFIG]) + _CONFIG.pack(
            _uint("Config.seq", msg.seq, _U16),
            _uint("Config.sample_period_us", msg.sample_period_us, _U32))
    if isinstance(msg, Ack):
        return bytes([FrameType.ACK]) + _ACK.pack(
            _enum("Ack.ref_type", msg.ref_type, FrameType, _REQUEST_TYPES),
            _uint("Ack.ref_seq", msg.ref_seq, _U16))
    if isinstance(msg, Nack):
        return bytes([FrameType.NACK]) + _NACK.pack(
            _enum("Nack.ref_type", msg.ref_type, FrameType, _REQUEST_TYPES),
            _uint("Nack.ref_seq", msg.ref_seq, _U16),
            _enum("Nack.reason", msg.reason, NackReason))
    raise ProtocolError(f"encode: expected a protocol message (Hello, HelloAck, Sample, Command, "
                        f"Config, Ack, Nack), got {type(msg).__name__}", "type")


def encode(msg: Message) -> bytes:
    """Complete wire frame of ``msg``, ending with the 0x00 delimiter.

    Raises:
        ProtocolError: a field does not fit the wire format (non-finite or out-of-float32-range
            float, integer outside its width, unknown enum code, reserved status bit, bad
            firmware id) - reason ``"value"``; ``msg`` is not a message - reason ``"type"``.
            The message names the field and the value. Physical range checks are not done here.
    """
    return pack_frame(_encode_payload(msg))


# ---------------------------------------------------------------------------------------------
# decoding


def _check_len(ftype: FrameType, body: bytes, expected: int) -> None:
    if len(body) != expected:
        raise ProtocolError(f"{ftype.name} frame: body of {len(body)} bytes, expected {expected}",
                            "length")


def _finite(ftype: FrameType, name: str, value: float) -> float:
    if not math.isfinite(value):
        raise ProtocolError(f"{ftype.name} frame: {name} is not finite ({value!r})")
    return value


def _dec_enum(ftype: FrameType, name: str, value: int, enum: type[IntEnum],
              allowed: tuple[Any, ...] = ()) -> Any:
    try:
        member = enum(value)
    except ValueError:
        raise ProtocolError(f"{ftype.name} frame: unknown {name} code {value}") from None
    if allowed and member not in allowed:
        raise ProtocolError(f"{ftype.name} frame: {name} {member.name} not allowed here")
    return member


def _decode_sample(body: bytes, t: FrameType = FrameType.SAMPLE) -> Sample:
    counts: tuple[int, int] | None = None
    if t == FrameType.SAMPLE_V2:
        _check_len(t, body, _SAMPLE_V2.size)
        seq, t_us, sun, car, cur, b1, b2, b3, status, c_sun, c_out = _SAMPLE_V2.unpack(body)
        counts = (c_sun, c_out)
    else:
        _check_len(t, body, _SAMPLE.size)
        seq, t_us, sun, car, cur, b1, b2, b3, status = _SAMPLE.unpack(body)
    if status & ~_STATUS_MASK:
        raise ProtocolError(f"{t.name} frame: reserved status bits set (0x{status:04X})")
    return Sample(seq, t_us, _finite(t, "sun_speed", sun), _finite(t, "carrier3_speed", car),
                  _finite(t, "motor_current", cur),
                  (_finite(t, "brake_currents[0]", b1), _finite(t, "brake_currents[1]", b2),
                   _finite(t, "brake_currents[2]", b3)),
                  Status(status), counts)


def _decode_sample_v2(body: bytes) -> Sample:
    return _decode_sample(body, FrameType.SAMPLE_V2)


def _decode_command(body: bytes) -> Command:
    t = FrameType.COMMAND
    _check_len(t, body, _COMMAND.size)
    seq, mode, sp, b1, b2, b3 = _COMMAND.unpack(body)
    return Command(seq, _dec_enum(t, "mode", mode, Mode), _finite(t, "setpoint", sp),
                   (_finite(t, "brake_currents[0]", b1), _finite(t, "brake_currents[1]", b2),
                    _finite(t, "brake_currents[2]", b3)))


def _decode_hello(body: bytes) -> Hello:
    _check_len(FrameType.HELLO, body, _HELLO.size)
    return Hello(_HELLO.unpack(body)[0])


def _decode_hello_ack(body: bytes) -> HelloAck:
    t = FrameType.HELLO_ACK
    if len(body) < _HELLO_ACK_HEAD.size:
        _check_len(t, body, _HELLO_ACK_HEAD.size)
    version = int.from_bytes(body[:2], "little")
    sun_cpr = out_cpr = 0
    if version < 2:
        head = _HELLO_ACK_HEAD
        version, period, watchdog, n = head.unpack_from(body)
    else:  # the version-2 head carries the encoders' counts per revolution
        head = _HELLO_ACK_HEAD_V2
        if len(body) < head.size:
            _check_len(t, body, head.size)
        version, period, watchdog, sun_cpr, out_cpr, n = head.unpack_from(body)
    if n > FIRMWARE_ID_MAX_LEN:
        raise ProtocolError(f"HELLO_ACK frame: firmware id length {n} exceeds "
                            f"{FIRMWARE_ID_MAX_LEN}")
    _check_len(t, body, head.size + n)
    fid = body[head.size:]
    if not all(0x20 <= c <= 0x7E for c in fid):
        raise ProtocolError(f"HELLO_ACK frame: firmware id is not printable ASCII ({fid!r})")
    return HelloAck(version, period, watchdog, fid.decode("ascii"), sun_cpr, out_cpr)


def _decode_config(body: bytes) -> Config:
    _check_len(FrameType.CONFIG, body, _CONFIG.size)
    seq, period = _CONFIG.unpack(body)
    return Config(seq, period)


def _decode_ack(body: bytes) -> Ack:
    t = FrameType.ACK
    _check_len(t, body, _ACK.size)
    ref, seq = _ACK.unpack(body)
    return Ack(_dec_enum(t, "ref_type", ref, FrameType, _REQUEST_TYPES), seq)


def _decode_nack(body: bytes) -> Nack:
    t = FrameType.NACK
    _check_len(t, body, _NACK.size)
    ref, seq, reason = _NACK.unpack(body)
    return Nack(_dec_enum(t, "ref_type", ref, FrameType, _REQUEST_TYPES), seq,
                _dec_enum(t, "reason", reason, NackReason))


_DECODERS: dict[int, Any] = {
    FrameType.HELLO: _decode_hello,
    FrameType.HELLO_ACK: _decode_hello_ack,
    FrameType.SAMPLE: _decode_sample,
    FrameType.SAMPLE_V2: _decode_sample_v2,
    FrameType.COMMAND: _decode_command,
    FrameType.CONFIG: _decode_config,
    FrameType.ACK: _decode_ack,
    FrameType.NACK: _decode_nack,
}


def decode_frame(frame: bytes) -> Message:
    """Message carried by one frame.

    Args:
        frame: the COBS-encoded bytes between two delimiters; one trailing 0x00 delimiter is
            allowed (so ``decode_frame(encode(m)) == m``, up to float32 rounding).

    Raises:
        ProtocolError: with ``reason`` ``"empty"``, ``"oversize"`` (more than
            :data:`MAX_FRAME_LEN` bytes), ``"cobs"``, ``"truncated"`` (fewer than 3 payload
            bytes), ``"crc"``, ``"unknown_type"``, ``"length"`` (wrong body length for the
            type) or ``"value"`` (non-finite float, unknown enum code, reserved status bit,
            bad firmware id). Nothing else is raised for any input of type bytes.
    """
    data = bytes(frame)
    if data.endswith(b"\x00"):
        data = data[:-1]
    if not data:
        raise ProtocolError("empty frame", "empty")
    if len(data) > MAX_FRAME_LEN:
        raise ProtocolError(f"frame of {len(data)} bytes exceeds the maximum of {MAX_FRAME_LEN}",
                            "oversize")
    raw = cobs_decode(data)
    if len(raw) < 1 + _CRC.size:
        raise ProtocolError(f"frame payload of {len(raw)} bytes is shorter than type + CRC (3)",
                            "truncated")
    payload = raw[:-_CRC.size]
    sent = _CRC.unpack(raw[-_CRC.size:])[0]
    computed = crc16(payload)
    if sent != computed:
        raise ProtocolError(f"CRC mismatch: frame carries 0x{sent:04X}, "
                            f"payload gives 0x{computed:04X}", "crc")
    decoder = _DECODERS.get(payload[0])
    if decoder is None:
        raise ProtocolError(f"unknown frame type 0x{payload[0]:02X}", "unknown_type")
    msg: Message = decoder(payload[1:])
    return msg


# ---------------------------------------------------------------------------------------------
# streaming


class FrameDecoder:
    """Streaming decoder: bytes in, messages out, never raises on malformed input.

    Bytes are collected up to each 0x00 delimiter and decoded with :func:`decode_frame`. A bad
    frame is dropped and counted, and decoding resumes at the next delimiter (self-
    synchronisation). Empty frames (consecutive delimiters) are ignored silently. A frame
    longer than ``max_frame_len`` is dropped as soon as the limit is passed (bounded memory) and
    the rest of it up to the next delimiter is discarded.

    Before the first delimiter the decoder may be *unsynchronised* (``synced=False``, e.g. right
    after opening a port in the middle of a frame): a fragment that does not decode there is
    discarded and counted in ``bytes_discarded`` only, not as a bad frame.

    Counters (cumulative, never reset by :meth:`reset`):
        frames_good: frames decoded into a message.
        frames_bad: frames dropped as malformed (including oversize ones).
        crc_errors: the subset of ``frames_bad`` that failed the CRC.
        bytes_discarded: encoded bytes of dropped frames and unsynchronised fragments.
        errors_by_reason: ``frames_bad`` split by :attr:`ProtocolError.reason`.
        last_error: the last :class:`ProtocolError` of a dropped frame, or ``None``.
    """

    def __init__(self, max_frame_len: int = MAX_FRAME_LEN, *, synced: bool = True) -> None:
        """Args:
            max_frame_len: longest accepted encoded frame [bytes], >= 1.
            synced: whether the first byte fed starts a frame.
        """
        if isinstance(max_frame_len, bool) or not isinstance(max_frame_len, int) \
                or max_frame_len < 1:
            raise ProtocolError(f"FrameDecoder: max_frame_len must be a positive integer, "
                                f"got {max_frame_len!r}")
        self.max_frame_len = max_frame_len
        self.frames_good = 0
        self.frames_bad = 0
        self.crc_errors = 0
        self.bytes_discarded = 0
        self.errors_by_reason: dict[str, int] = {}
        self.last_error: ProtocolError | None = None
        self._buf = bytearray()
        self._overflow = False
        self._synced = synced

    @property
    def pending(self) -> int:
        """Bytes of an incomplete frame currently buffered."""
        return len(self._buf)

    def reset(self, *, synced: bool = False) -> None:
        """Drop any partial frame (counted in ``bytes_discarded``); counters are kept.

        Call it when the byte stream was interrupted (port reopened); ``synced=False`` treats
        the first fragment after the reset as unsynchronised.
        """
        self.bytes_discarded += len(self._buf)
        self._buf.clear()
        self._overflow = False
        self._synced = synced

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        """Consume ``data`` and return the messages of every frame it completes, in order."""
        out: list[Message] = []
        chunk = bytes(data)
        start = 0
        while True:
            end = chunk.find(b"\x00", start)
            if end < 0:
                self._append(chunk[start:])
                return out
            self._append(chunk[start:end])
            self._end_frame(out)
            start = end + 1

    def _append(self, part: bytes) -> None:
        if not part:
            return
        if self._overflow:
            self.bytes_discarded += len(part)
            return
        self._buf += part
        if len(self._buf) > self.max_frame_len:
            self.bytes_discarded += len(self._buf)
            self._buf.clear()
            self._overflow = True

    def _bad(self, err: ProtocolError) -> None:
        self.frames_bad += 1
        if err.reason == "crc":
            self.crc_errors += 1
        self.errors_by_reason[err.reason] = self.errors_by_reason.get(err.reason, 0) + 1
        self.last_error = err

    def _end_frame(self, out: list[Message]) -> None:
        synced = self._synced
        self._synced = True
        if self._overflow:
            self._overflow = False
            if synced:
                self._bad(ProtocolError(f"frame longer than {self.max_frame_len} bytes dropped",
                                        "oversize"))
            return
        if not self._buf:
            return
        frame = bytes(self._buf)
        self._buf.clear()
        try:
            msg = decode_frame(frame)
        except ProtocolError as err:
            self.bytes_discarded += len(frame)
            if synced:
                self._bad(err)
            return
        self.frames_good += 1
        out.append(msg)


@dataclass(frozen=True, slots=True)
class SequenceUpdate:
    """What one sample told :class:`SequenceTracker`.

    Attributes:
        lost: samples missing between the previous sample and this one (0 if none or on reset).
        reset: the controller restarted (sequence went backwards or the clock did not advance);
            this sample starts a new run.
        duplicate: same sequence number and clock as the previous sample (ignore it).
    """

    lost: int = 0
    reset: bool = False
    duplicate: bool = False


class SequenceTracker:
    """Counts lost samples and controller resets from (sequence number, clock) pairs.

    ``seq`` is a u32 that wraps modulo 2**32; a forward step of ``d`` (modulo 2**32, d < 2**31)
    means ``d - 1`` samples were lost. A backward step (``d >= 2**31``), or a forward step whose
    clock ``t_us`` does not increase, is a controller reset: it is counted and the sample starts
    a new run without counting losses. Same ``seq`` and same ``t_us`` is a duplicate.

    Counters: ``samples`` (all updates), ``lost``, ``resets``, ``duplicates``.
    """

    _MOD = 1 << 32
    _HALF = 1 << 31

    def __init__(self) -> None:
        self.samples = 0
        self.lost = 0
        self.resets = 0
        self.duplicates = 0
        self.last_seq: int | None = None
        self.last_t_us: int | None = None

    def forget(self) -> None:
        """Forget the previous sample (the next one starts a run); counters are kept."""
        self.last_seq = None
        self.last_t_us = None

    def update(self, seq: int, t_us: int) -> SequenceUpdate:
        """Account one sample with sequence number ``seq`` (u32) and clock ``t_us`` [µs]."""
        self.samples += 1
        last_seq, last_t = self.last_seq, self.last_t_us
        if last_seq is None or last_t is None:
            self.last_seq, self.last_t_us = seq, t_us
            return SequenceUpdate()
        step = (seq - last_seq) % self._MOD
        if step == 0 and t_us == last_t:
            self.duplicates += 1
            return SequenceUpdate(duplicate=True)
        self.last_seq, self.last_t_us = seq, t_us
        if step == 0 or step >= self._HALF or t_us <= last_t:
            self.resets += 1
            return SequenceUpdate(reset=True)
        self.lost += step - 1
        return SequenceUpdate(lost=step - 1)
