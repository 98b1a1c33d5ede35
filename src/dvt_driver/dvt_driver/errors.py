"""Errors raised by the dvt_driver core.

Every error names what was wrong (port, frame field, value) so that a user can act on it
without reading the code. All of them derive from :class:`DvtDriverError`.
"""

from __future__ import annotations


class DvtDriverError(Exception):
    """Base class of every error raised by :mod:`dvt_driver`."""


class ProtocolError(DvtDriverError, ValueError):
    """A wire frame or a message is malformed (see ``docs/protocol.md``).

    Raised by :func:`dvt_driver.protocol.decode_frame` on anything it cannot decode and by
    :func:`dvt_driver.protocol.encode` on a message that cannot be put on the wire.

    Attributes:
        reason: a short machine-readable class of the fault, one of ``"empty"``,
            ``"oversize"``, ``"cobs"``, ``"truncated"``, ``"crc"``, ``"unknown_type"``,
            ``"length"``, ``"value"`` (a field's value is not allowed, e.g. a NaN float, an
            unknown enum code, an integer that does not fit its width) and ``"type"``
            (the object given to ``encode`` is not a protocol message).
    """

    def __init__(self, message: str, reason: str = "value") -> None:
        super().__init__(message)
        self.reason = reason


class LinkError(DvtDriverError):
    """The serial link cannot be opened or was used wrongly (bad port, baud rate, timeout).

    Runtime failures of an open link (device vanished, write failed) are not raised: they move
    the link to ``DISCONNECTED`` and are counted (see :class:`dvt_driver.link.SerialLink`).
    """
