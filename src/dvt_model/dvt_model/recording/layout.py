"""The on-disk layout of a DVT recording (pure; constants only).

A recording is a rosbag2 directory: ``metadata.yaml`` (rosbag2 version 9) next to one ``.mcap``
file (profile ``ros2``, schema encoding ``ros2msg``, message encoding ``cdr``, ROS 2 Jazzy
types), optionally with a ``truth.yaml`` sidecar (simulation only) and a ``run.yaml`` sidecar
(how ``dvt-launch`` made the run); :mod:`~dvt_model.recording.sidecar` reads and writes the three
YAML files. Topic names and joint names are the contract's (:mod:`dvt_model.contract`).
"""

from __future__ import annotations

from pathlib import Path

ROSBAG2_VERSION = 9
"""``metadata.yaml`` version written (as ``rosbags`` writes it for Jazzy)."""
ROS_DISTRO = "jazzy"
LIBRARY = "dvt-recorder"
"""The ``library`` field of the MCAP header of every bag written here."""
METADATA_FILE = "metadata.yaml"
TRUTH_FILE = "truth.yaml"
"""Sidecar with the simulated plant's hidden truth (see :func:`~.write.write_run`)."""
RUN_FILE = "run.yaml"
"""Sidecar saying how ``dvt-launch`` made the run (command, settings, the bag check)."""
RECOVER_HINT = "dvt-bag recover"
"""The command that rebuilds a killed recording (named in errors)."""
MCAP_MAGIC = b"\x89MCAP0\r\n"
NS = 1_000_000_000
"""Nanoseconds per second."""


def recover_hint(path: Path) -> str:
    """The hint appended to a read error: run :data:`RECOVER_HINT` where it can help (an
    ``.mcap`` file, or a directory holding one: a killed recording); otherwise say that ``path``
    is not a bag directory (a README is not a killed recording)."""
    if path.is_file():
        has_mcap = path.suffix == ".mcap"
    else:
        has_mcap = path.is_dir() and any(path.glob("*.mcap"))
    if has_mcap:
        return f" (if the recording was killed, run `{RECOVER_HINT} {path}`)"
    return (" (not a bag directory: a recording is a directory holding metadata.yaml and an "
            ".mcap file)")
