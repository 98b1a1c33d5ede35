"""Recordings: the only code that writes, reads, pairs, recovers and summarises them (pure).

A recording is a rosbag2 directory (``metadata.yaml`` + one ``.mcap`` file, CDR, ROS 2 Jazzy
types; see :mod:`~dvt_model.recording.layout`). Topic and joint names are the contract's
(:mod:`dvt_model.contract`). Modules, by concern:

* :mod:`~dvt_model.recording.cdr` - JointState CDR encode/decode, the one :func:`typestore`, the
  one stamp decoder of raw CDR :func:`raw_stamp_ns`;
* :mod:`~dvt_model.recording.mcapindex` - fast reader of indexed MCAP files;
* :mod:`~dvt_model.recording.read` - :func:`read_topics`, :func:`read_run`, ... and the one series
  type :class:`TopicSeries`;
* :mod:`~dvt_model.recording.messages` - any topic as raw messages in log-time order
  (:class:`BagMessages`, :func:`first_log_time`);
* :mod:`~dvt_model.recording.sidecar` - the one reader of ``metadata.yaml``, ``truth.yaml`` and
  ``run.yaml`` (:func:`read_metadata`, :func:`read_truth`, :func:`read_run_info`, ...);
* :mod:`~dvt_model.recording.write` - the one writer :class:`BagRecorder` (crash-safe, used live
  by ``dvt-recorder``) and its offline wrappers :func:`write_bag`, :func:`write_run`,
  :func:`write_topics`;
* :mod:`~dvt_model.recording.pairing` - the one stamp pairing (:func:`pair_stamps` offline,
  :class:`LivePairer` live);
* :mod:`~dvt_model.recording.recover` - :func:`recover` a killed recording, :func:`is_readable`;
* :mod:`~dvt_model.recording.summary` - :func:`bag_summary` (``dvt-bag info``);
* :mod:`~dvt_model.recording.ring` - :class:`RollingRecorder` (the last N minutes in segments of
  the one writer) and :func:`write_snapshot` (a window of it as a normal bag).

Errors: :class:`~dvt_model.errors.BagError` (reading, contract violations) and its subclass
:class:`~dvt_model.errors.RecordingError` (writing, recovering, summarising).
"""

from dvt_model.errors import BagError, RecordingError
from dvt_model.recording.cdr import (
    joint_state,
    joint_state_cdr,
    message_definition,
    raw_stamp_ns,
    restamp,
    typestore,
)
from dvt_model.recording.layout import METADATA_FILE, RECOVER_HINT, RUN_FILE, TRUTH_FILE
from dvt_model.recording.messages import BagMessage, BagMessages, decode, first_log_time
from dvt_model.recording.pairing import LivePairer, Pairing, pair_stamps
from dvt_model.recording.read import (
    FIELDS,
    Run,
    TopicSeries,
    read_run,
    read_topic_series,
    read_topics,
    sample_period,
)
from dvt_model.recording.recover import RecoverResult, is_readable, recover
from dvt_model.recording.ring import RollingRecorder, SnapshotPlan, SnapshotResult, write_snapshot
from dvt_model.recording.sidecar import (
    changes_applied,
    is_bag,
    parse_truth,
    read_metadata,
    read_run_info,
    read_truth,
    write_run_info,
    write_truth,
)
from dvt_model.recording.summary import BagSummary, TopicSummary, bag_summary
from dvt_model.recording.write import (
    DEFAULT_FLUSH_PERIOD,
    BagRecorder,
    Stream,
    write_bag,
    write_run,
    write_topics,
)

__all__ = [
    "DEFAULT_FLUSH_PERIOD",
    "FIELDS",
    "METADATA_FILE",
    "RECOVER_HINT",
    "RUN_FILE",
    "TRUTH_FILE",
    "BagError",
    "BagMessage",
    "BagMessages",
    "BagRecorder",
    "BagSummary",
    "LivePairer",
    "Pairing",
    "RecordingError",
    "RecoverResult",
    "RollingRecorder",
    "Run",
    "SnapshotPlan",
    "SnapshotResult",
    "Stream",
    "TopicSeries",
    "TopicSummary",
    "bag_summary",
    "changes_applied",
    "decode",
    "first_log_time",
    "is_bag",
    "is_readable",
    "joint_state",
    "joint_state_cdr",
    "message_definition",
    "pair_stamps",
    "parse_truth",
    "raw_stamp_ns",
    "read_metadata",
    "read_run",
    "read_run_info",
    "read_topic_series",
    "read_topics",
    "read_truth",
    "recover",
    "restamp",
    "sample_period",
    "typestore",
    "write_bag",
    "write_run",
    "write_run_info",
    "write_snapshot",
    "write_topics",
    "write_truth",
]
