"""Building ids as NATS tokens, and the messages the cluster's processes exchange."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.buildings.calls import ListAnchors
from server.cluster import messages
from server.cluster.names import building_token, calls_subject, live_subject, receipts_subject, token_building
from server.errors import InvalidInputError, ProblemError

TOKEN = re.compile(r"[A-Za-z0-9_-]+")  # what a subject token and a key-value key may both hold


@given(st.text(min_size=1, max_size=64))
def test_any_building_id_is_one_token_and_comes_back(building_id: str) -> None:
    token = building_token(building_id)
    assert TOKEN.fullmatch(token)
    assert token_building(token) == building_id
    assert live_subject(building_id).split(".")[-1] == token
    assert calls_subject(building_id).count(".") == 2


def test_a_token_it_did_not_make_is_refused() -> None:
    with pytest.raises(ValueError, match="not a building token"):
        token_building("hq")
    with pytest.raises(ValueError, match="not a building token"):
        token_building("bzz")


def test_receipts_come_back_on_a_subject_per_request() -> None:
    assert receipts_subject("f1", 7) == "crowdslam.receipts.f1.7"
    assert receipts_subject("f1") == "crowdslam.receipts.f1.*"


def test_answers_carry_values_and_errors() -> None:
    assert messages.decode_answer(messages.encode_answer(b'{"status":"applied"}')) == b'{"status":"applied"}'
    with pytest.raises(ProblemError, match="bad batch") as refused:
        messages.decode_answer(messages.encode_answer(InvalidInputError("bad batch")))
    assert refused.value.status == InvalidInputError.status
    # an unexpected error crosses as a RuntimeError naming it (the front answers 500 and logs it)
    with pytest.raises(RuntimeError, match="KeyError"):
        messages.decode_answer(messages.encode_answer(KeyError("x")))
    assert messages.decode_call(messages.encode_call(ListAnchors())) == ListAnchors()
    texts = ['{"type":"position"}', '{"type":"anchor"}']
    assert messages.decode_live(messages.encode_live(texts)) == texts
    assert messages.decode_live(b"") == []
