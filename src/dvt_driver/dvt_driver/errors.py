"""Every error class of :mod:`dvt_driver` (link, session, safety, plant, experiments, launcher).

Every error names what was wrong (port, frame field, value) so that a user can act on it
without reading the code. All of them derive from :class:`DvtDriverError`.
"""

from __future__ import annotations


class DvtDriverError(Exception):
    """Base class of every error raised by :mod:`dvt_driver`."""


class ProtocolError(DvtDriverError, ValueError):
    """A wire frame or a message is malformed (see ``docs/protocol.md``).

    Raised by :func:`dvt_driver.link.protocol.decode_frame` on anything it cannot decode and by
    :func:`dvt_driver.link.protocol.encode` on a message that cannot be put on the wire.

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
    the link to ``DISCONNECTED`` and are counted (see
    :class:`dvt_driver.link.serial_link.SerialLink`).
    """


class SessionError(DvtDriverError, ValueError):
    """A controller-session setting or input is invalid (see :mod:`dvt_driver.link.session`)."""


class ClockError(DvtDriverError, ValueError):
    """Invalid :class:`~dvt_driver.link.clock.ClockMapper` setting or input (names the argument
    and value)."""


class SafetyConfigError(DvtDriverError, ValueError):
    """A driver setting (limit, timeout, shift setting, port, rate) is invalid; names it and
    its value (:mod:`dvt_driver.link.safety`, :mod:`dvt_driver.link.settings`)."""


class CommandRefusedError(DvtDriverError, ValueError):
    """A command was refused; ``str(exc)`` is the reason (names the field and the value).

    Attributes:
        what: the command kind (``motor_current``, ``sun_speed``, ``brake_currents``, ``gear``).
    """

    def __init__(self, what: str, reason: str) -> None:
        super().__init__(f"{what}: {reason}")
        self.what = what


class PlantError(DvtDriverError, ValueError):
    """The simulated plant was configured wrongly (the message names the setting and value)."""


class HiddenEffectsError(DvtDriverError, ValueError):
    """A hidden-effects file or mapping is invalid; the message names file, key and value."""


class ExperimentError(DvtDriverError, ValueError):
    """An experiment is unknown, badly parameterised or exceeds a limit (names what and where)."""


class LaunchError(DvtDriverError):
    """A child could not be started, died, or did not become ready (message says which)."""


class LaunchInterruptedError(DvtDriverError):
    """Ctrl-C / SIGTERM arrived during start-up or the run."""
