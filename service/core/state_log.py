"""When a state change is worth a log line: never one per frame, never more than one a second.

A state that flaps (a net at the edge of detection, a stream that stutters, an output that
starts and stops on a loaded machine) must not fill the journal: each topic logs at most once
per `min_interval_s`; the changes in between are counted and the next line says how many there
were. Pure: the caller says what time it is and writes the line.
"""

from __future__ import annotations


class StateLog:
    """Decides when a state change is logged: at most once per `min_interval_s` per topic.

    The caller reports the current state every time it looks (every frame, every status); a
    line is due when the state differs from the one last logged and the topic has been quiet
    long enough. Changes in between are counted, and the line that follows names the state in
    force then, so the log always ends on the truth, however fast the state flapped.
    """

    def __init__(self, min_interval_s: float = 1.0) -> None:
        self.min_interval_s = min_interval_s
        self._logged: dict[str, object] = {}
        self._current: dict[str, object] = {}
        self._changes: dict[str, int] = {}
        self._last_line: dict[str, float] = {}

    def update(self, topic: str, state: object, now: float) -> tuple[bool, object, int]:
        """(log now?, the state last logged, changes since it beyond the one being logged)."""
        if topic in self._current and self._current[topic] != state:
            self._changes[topic] = self._changes.get(topic, 0) + 1
        self._current[topic] = state
        if topic not in self._logged:
            self._logged[topic] = state  # the initial state is not a change
            self._changes[topic] = 0
            return False, state, 0
        previous = self._logged[topic]
        if state == previous:
            return False, previous, 0
        last = self._last_line.get(topic)
        if last is not None and now - last < self.min_interval_s:
            return False, previous, 0
        changes = self._changes.get(topic, 1)
        self._logged[topic] = state
        self._changes[topic] = 0
        self._last_line[topic] = now
        return True, previous, max(0, changes - 1)


def not_logged_note(between: int) -> str:
    """The tail of a state-change line that followed `between` changes not logged."""
    return f" (after {between} more change(s) not logged)" if between else ""
