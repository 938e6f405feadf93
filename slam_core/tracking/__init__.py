"""One building's live tracking: every user's filter, the crowd map and encounters, driven alike by the
server, the replays and the evaluation."""
