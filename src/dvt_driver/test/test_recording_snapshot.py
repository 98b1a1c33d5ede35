"""The recorder's snapshot request (pure part of the rolling mode)."""

from __future__ import annotations

import json

import pytest

from dvt_driver.recording.node import SNAPSHOT_REQUEST, SNAPSHOT_RESULT, parse_snapshot_request
from dvt_model.errors import RecordingError


def test_valid_request_is_parsed() -> None:
    req = parse_snapshot_request(json.dumps({"from": 10.5, "to": 12, "out": "/tmp/x", "id": 7}))
    assert req == (10.5, 12.0, "/tmp/x", 7)
    assert parse_snapshot_request('{"from": 1, "to": 1, "out": "d"}')[3] is None


@pytest.mark.parametrize(("text", "needle"), [
    ("nope", "not JSON"),
    ("[1, 2]", "JSON object"),
    ('{"to": 2, "out": "d"}', "'from'"),
    ('{"from": -1, "to": 2, "out": "d"}', "'from'"),
    ('{"from": 1, "to": "x", "out": "d"}', "'to'"),
    ('{"from": 3, "to": 2, "out": "d"}', "before 'from'"),
    ('{"from": 1, "to": 2}', "'out'"),
    ('{"from": 1, "to": 2, "out": ""}', "'out'"),
])
def test_bad_requests_name_the_field(text: str, needle: str) -> None:
    with pytest.raises(RecordingError, match=needle):
        parse_snapshot_request(text)


def test_topic_names() -> None:
    assert SNAPSHOT_REQUEST == "/dvt/recorder/snapshot"
    assert SNAPSHOT_RESULT == "/dvt/recorder/snapshot_result"
