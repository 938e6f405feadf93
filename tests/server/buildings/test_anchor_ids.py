from __future__ import annotations

from server.buildings.anchor_ids import AnchorIds


def test_crowd_anchors_get_the_next_free_number_after_every_linked_one() -> None:
    ids = AnchorIds()
    ids.link(0, "a-3", None)
    ids.link(1, "lobby-stairs", "Lobby stairs")
    assert ids.public_id(2) == "a-4"
    assert ids.public_id(2) == "a-4"  # asked again: the same id
    ids.link(5, "a-5", None)
    assert ids.public_id(6) == "a-6"
    assert ids.index == {"a-3": 0, "lobby-stairs": 1, "a-4": 2, "a-5": 5, "a-6": 6}
    assert ids.labels[1] == "Lobby stairs"
    assert ids.labels[2] is None


def test_an_operator_id_in_the_crowd_pattern_is_skipped_not_reused() -> None:
    ids = AnchorIds()
    ids.index["a-0"] = 9  # taken without bumping the counter (an id restored from SQL under another index)
    assert ids.public_id(1) == "a-1"
