"""Errors that end a request, each with its HTTP status and Problem body; mapped to HTTP in one place."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from pydantic import ValidationError

from schemas.errors import FieldProblem, Problem


class ProblemError(Exception):
    """Base: an error that a client caused and can act on."""

    status = 400
    title = "Bad request"
    retry_after_s: float | None = None
    """When set, the answer carries ``Retry-After``: the same request may succeed then."""

    def __init__(self, detail: str, errors: Sequence[FieldProblem] = ()) -> None:
        super().__init__(detail)
        self.detail = detail
        self.errors = list(errors)

    def to_problem(self) -> Problem:
        return Problem(title=self.title, status=self.status, detail=self.detail, errors=self.errors)

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """Pickled as what it says (status, title, detail, errors, when to retry): it crosses from a
        building's process."""
        return _problem_error, (self.status, self.title, self.detail, self.errors, self.retry_after_s)


def _problem_error(
    status: int, title: str, detail: str, errors: list[FieldProblem], retry_after_s: float | None = None
) -> ProblemError:
    error = ProblemError(detail, errors)
    error.status = status
    error.title = title
    error.retry_after_s = retry_after_s
    return error


class MalformedBodyError(ProblemError):
    status = 400
    title = "Malformed request body"


class BodyTooLargeError(ProblemError):
    status = 413
    title = "Request body too large"

    def __init__(self, n_bytes: int, limit: int, what: str = "") -> None:
        if what:  # a compressed body: counted as it was inflated, and stopped past the limit
            text = (
                f"the body has more than {limit} bytes {what}; at most {limit} bytes are accepted per request"
            )
        else:
            text = f"the body has {n_bytes} bytes; at most {limit} bytes are accepted per request"
        super().__init__(text)
        self.n_bytes = n_bytes
        self.limit = limit


class UnsupportedEncodingError(ProblemError):
    status = 415
    title = "Unsupported content encoding"

    def __init__(self, encoding: str) -> None:
        super().__init__(f"Content-Encoding {encoding[:40]!r} is not accepted: send gzip, or no encoding")


class InvalidInputError(ProblemError):
    status = 422
    title = "Invalid input"

    @classmethod
    def from_validation_error(cls, error: ValidationError, title: str | None = None) -> InvalidInputError:
        problems = [field_problem(e) for e in error.errors(include_url=False)]
        noun = "field is" if len(problems) == 1 else "fields are"
        instance = cls(
            f"{len(problems)} {noun} invalid: " + "; ".join(f"{p.loc}: {p.msg}" for p in problems[:5]),
            problems,
        )
        if title is not None:
            instance.title = title
        return instance


class UnauthorizedError(ProblemError):
    status = 401
    title = "Unauthorized"


class ForbiddenError(ProblemError):
    status = 403
    title = "Forbidden"


class NotFoundError(ProblemError):
    status = 404
    title = "Not found"


class ConflictError(ProblemError):
    status = 409
    title = "Conflict"


class UnexpectedError(ProblemError):
    """Any error no handler names: logged for the operators, answered without its text."""

    status = 500
    title = "Internal server error"

    def __init__(self) -> None:
        super().__init__("the server could not answer this request; the error was logged for its operators")


class BatchFailedError(ProblemError):
    """A batch the server could not apply for a reason of its own (logged, counted, named in ``/healthz``);
    nothing of it was kept. The answer says so and no more: the error's text is the server's, not the
    client's."""

    status = 500
    title = "Internal server error"

    def __init__(self) -> None:
        super().__init__(
            "the server could not apply this batch: nothing of it was kept, and the error was logged for the "
            "server's operators (/healthz names the building); sending it again may fail the same way"
        )


class TooManyRequestsError(ProblemError):
    """The caller is over its rate; it may retry after ``retry_after_s``."""

    status = 429
    title = "Too many requests"

    def __init__(self, detail: str, retry_after_s: float) -> None:
        super().__init__(detail)
        self.retry_after_s = retry_after_s


class DiskFullError(ProblemError):
    """The database's disk is full: nothing of the request was kept, and it may be sent again once there
    is room (503, as a phone already handles: ``Retry-After``)."""

    status = 503
    title = "Service unavailable"

    def __init__(self) -> None:
        super().__init__("the server's disk is full: nothing of this was kept; send it again later")
        self.retry_after_s = DISK_FULL_RETRY_S


DISK_FULL_RETRY_S = 60.0


class ServiceUnavailableError(ProblemError):
    """The request can be sent again (a building's process is restarting, its worker is being replaced)."""

    status = 503
    title = "Service unavailable"

    def __init__(self, detail: str, retry_after_s: float | None = None) -> None:
        super().__init__(detail)
        self.retry_after_s = retry_after_s


class BuildingUnavailableError(ServiceUnavailableError):
    """The building could not be loaded (an error of the server's, logged and named in ``/healthz``): nothing
    of the request was kept; it may be sent again after ``retry_after_s``, when loading is tried again."""

    def __init__(self, building_id: str, retry_after_s: float) -> None:
        super().__init__(
            f"building {building_id!r} cannot be loaded now: nothing of this was kept; send it again later "
            "(the error was logged for the server's operators, and /healthz names the building)",
            retry_after_s,
        )


def field_problem(error: Any) -> FieldProblem:
    """One pydantic error as a FieldProblem with a dotted path ('steps.0.length_m')."""
    loc = ".".join(str(part) for part in error.get("loc", ())) or "body"
    return FieldProblem(
        loc=loc, msg=str(error.get("msg", "invalid")), type=str(error.get("type", "value_error"))
    )


PROBLEM_MEDIA_TYPE = "application/problem+json"


def problem_response_parts(problem: Problem) -> tuple[int, bytes, dict[str, str]]:
    """How every Problem goes on the wire, whichever path answers: status, body and headers (a 401 says
    which scheme to use)."""
    body = json.dumps(
        problem.model_dump(mode="json"), ensure_ascii=False, allow_nan=False, separators=(",", ":")
    ).encode()
    headers = {"content-type": PROBLEM_MEDIA_TYPE}
    if problem.status == 401:
        headers["www-authenticate"] = "Bearer"
    return problem.status, body, headers
