"""A building's groups of batches, the same wherever the building runs (a thread of the server, a process of
its own, a cluster's worker): when the next group starts (``GroupPacing``) and what running one gives back
(``GroupRunner.run``: each batch's answer, the live messages, the time it took). Only how
batches arrive and answers leave differs between those places (``handles``, ``process``)."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from schemas.live import LiveMessage
from server.buildings.host import BuildingHost
from server.buildings.submissions import Submission
from server.live.broadcast import live_json

MAX_GROUP = 256
"""Batches in one group at most: a group's transaction and tracker calls stay short enough for an operator's
call waiting behind it."""


class GroupPacing:
    """When a building's next group starts: a group pays a fixed cost (a transaction, the filters' and the
    encounters' calls) that its batches share, and applying each batch as soon as the building is free
    keeps the groups at one batch at moderate loads. So while the building is busy, which its last group
    says (it held more than one batch, or batches were waiting when it ended), the next group starts
    ``linger_s`` after the previous one started and takes what arrived meanwhile, as Kafka's ``linger.ms``
    and PostgreSQL's ``commit_delay`` do. A phone posting alone, or a replay posting one batch after
    another's receipt, never finds the building busy and never waits; a group that took longer than
    ``linger_s`` starts the next at once."""

    def __init__(self, linger_s: float) -> None:
        self.linger_s = linger_s
        self._started = -math.inf
        self._busy = False

    def wait_s(self, now: float) -> float:
        """How long a group whose first batch is here waits for more (``now``: ``time.monotonic()``)."""
        if not self._busy:
            return 0.0
        return max(0.0, self._started + self.linger_s - now)

    def start(self, now: float) -> None:
        self._started = now

    def end(self, size: int, waiting: bool) -> None:
        """The group that started last held ``size`` batches; ``waiting``: batches arrived meanwhile."""
        self._busy = size > 1 or waiting


@dataclass
class GroupAnswers:
    """What a group gives back to whoever waits for its batches."""

    answers: list[bytes | Exception]
    """Each batch's receipt as JSON, or the error that refused it (a ``ProblemError``; anything else is the
    server's: a process sends it ``transportable``)."""
    messages: list[LiveMessage]
    """The group's live messages."""
    seconds: float

    @functools.cached_property
    def texts(self) -> list[str]:
        """The live messages' JSON, serialised once for every subscriber (and every front). A building in
        the server's own process publishes the messages instead: the broadcaster serialises them only when
        the building has subscribers."""
        return [live_json(m) for m in self.messages]


class GroupRunner:
    """Runs a building's groups: the host's batch path, paced, with the answers in the form they leave in."""

    def __init__(self, host: BuildingHost) -> None:
        self.host = host
        self.pacing = GroupPacing(host.group_linger_s)

    def wait_s(self) -> float:
        """How long the group whose first batch has just arrived waits for more."""
        return self.pacing.wait_s(time.monotonic())

    def run(self, group: list[Submission], waiting: Callable[[], bool]) -> GroupAnswers:
        """``group`` through the building's batch path; ``waiting()``: whether batches arrived meanwhile
        (asked once it is done, for the next group's pacing)."""
        started = time.perf_counter()
        self.pacing.start(time.monotonic())
        try:
            result = self.host.process(group)
        except Exception as exc:  # every batch of the group fails with it (the host answers each alone)
            answers: list[bytes | Exception] = [exc] * len(group)
            messages: list[LiveMessage] = []
        else:
            answers = list(result.wire_receipts())
            messages = result.messages
        finally:
            self.pacing.end(len(group), waiting())
        return GroupAnswers(answers, messages, time.perf_counter() - started)
