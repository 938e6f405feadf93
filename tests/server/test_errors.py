"""Errors keep what they say when they cross a process boundary; a building accepts only its named calls."""

from __future__ import annotations

import pickle

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


def test_a_building_worker_refuses_calls_it_does_not_offer() -> None:
    import asyncio

    import pytest

    from server.buildings.handles import CALLS, BuildingThread

    assert "process" not in CALLS  # batches go through submit, in order
    worker = BuildingThread.__new__(BuildingThread)  # the check comes before the session is touched
    with pytest.raises(
        ValueError, match="unknown building call 'process'; valid: anchors, assign_device, context"
    ):
        asyncio.run(worker.call("process", []))
