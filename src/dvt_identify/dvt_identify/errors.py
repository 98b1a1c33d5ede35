"""Errors raised by the dvt_identify core.

Every error names what was wrong (bag, topic, field, file, column, value) so that a user can fix
the input without reading the code. The command-line tools print the message on one line and exit
with a non-zero status.
"""

from __future__ import annotations


class DvtIdentifyError(Exception):
    """Base class of every error raised by :mod:`dvt_identify`."""


class DataError(DvtIdentifyError, ValueError):
    """A recording cannot be used for identification.

    The message names the bag, the topic (and field/joint) and the problem: unreadable bag,
    missing topic, non-monotonic stamps, gaps, NaN, saturation, too little data, no excitation.
    """


class DescriptionError(DvtIdentifyError, ValueError):
    """An actuator description (YAML file) is invalid; the message names the file and key."""


class ImportDataError(DvtIdentifyError, ValueError):
    """Columns given to ``dvt-import`` are unusable (missing column, NaN, time not increasing)."""


class PushError(DvtIdentifyError, ValueError):
    """An identified model cannot be pushed to the model node (not the DVT structure, or a
    value the node would refuse); the message names the parameter and the value."""


class BenchError(DvtIdentifyError, ValueError):
    """A ``dvt-bench identify`` setting is unusable (the message names the option and value,
    e.g. a missing default recording)."""


class FitError(DvtIdentifyError, RuntimeError):
    """A fit could not be carried out (bad shapes, simulation diverged, no finite start)."""


class SupervisorError(DvtIdentifyError, ValueError):
    """A supervisor setting or event is unusable (the message names the parameter, e.g.
    ``supervisor.watch_s``, or the event field, and the value)."""


class BatchError(DvtIdentifyError, ValueError):
    """A ``dvt-identify-batch`` manifest, output folder or cluster is unusable; the message
    names the file, the job entry and the field (or the scheduler address)."""
