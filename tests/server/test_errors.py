"""Errors keep what they say when they cross a process boundary; a building takes only its typed calls."""

from __future__ import annotations

import pickle

import pytest

from schemas.errors import FieldProblem
from server.errors import BodyTooLargeError, InvalidInputError, NotFoundError, ProblemError


def test_problem_errors_survive_pickling_with_status_title_detail_and_errors() -> None:
    errors = [FieldProblem(loc="steps.0.length_m", msg="must be > 0", type="greater_than")]
    for original in (
        NotFoundError("no building 'x'"),
        BodyTooLargeError(5_000, 4_000),
        InvalidInputError("1 field is invalid", errors),
    ):
        copy = pickle.loads(pickle.dumps(original))
        assert isinstance(copy, ProblemError)
        assert copy.to_problem() == original.to_problem()
        assert str(copy) == str(original)


def test_a_building_takes_only_its_typed_calls_across_a_process() -> None:
    """A call crosses as it is (a frozen dataclass), and anything else is refused before it is run."""
    from server.buildings.calls import Call, GetAnchor, MergeAnchors
    from server.cluster import messages

    for call in (GetAnchor("lift"), MergeAnchors(("a", "b"))):
        again = pickle.loads(pickle.dumps(call))
        assert again == call
        assert isinstance(again, Call)
        assert messages.decode_call(messages.encode_call(call)) == call
    with pytest.raises(TypeError, match="not a building call: tuple"):
        messages.decode_call(pickle.dumps(("process", [])))
