"""Errors raised by the dvt_model core.

Every error names what was wrong (file, key, value) so that a user can fix the input
without reading the code.
"""

from __future__ import annotations


class DvtModelError(Exception):
    """Base class of every error raised by :mod:`dvt_model`."""


class ParameterError(DvtModelError, ValueError):
    """A parameter set (YAML file or mapping) is invalid.

    The message names the source, the key path and the offending value.
    """


class ModelError(DvtModelError, ValueError):
    """A model quantity is unusable (not SPD, wrong shape, not finite)."""


class SimulationError(DvtModelError, ValueError):
    """Inputs to a simulation are inconsistent (shapes, non-finite values, time order)."""


class BagError(DvtModelError, ValueError):
    """A recording is unreadable or violates the interface contract.

    The message names the bag path, the topic and the field.
    """


class RecordingError(BagError):
    """Writing, recovering or summarising a recording failed (``dvt-recorder``, ``dvt-bag``,
    :mod:`dvt_model.recording`); the message names the path, the topic and the reason."""


class ContractError(DvtModelError, ValueError):
    """A value violates the interface contract (topic data, a model-node parameter, an effect
    term): the message names the parameter or field, the value and what is admissible."""


class RecordingWarning(UserWarning):
    """A recording was read only in part (e.g. a killed recording's MCAP file read up to its last
    complete chunk); the message names the file, what was kept and how to repair it."""
