"""Collision events -> the start of each contact, as the lite backend reports collisions.

CARLA's collision sensor sends an event for every frame in which the ego touches another actor, on its
own stream: an event can arrive after the tick that produced it was read. A contact therefore is one
other actor with events no more than :data:`CONTACT_GAP` frames apart, whatever order they arrive in; a
late event of an ongoing contact is part of it, never a new collision. An event that arrives after its
frame was read and starts a contact is reported with the next tick (one step late) rather than lost.
"""

from __future__ import annotations

CONTACT_GAP = 3  # [frames] a contact has ended after this many frames without an event for it


class ContactTracker:
    """Feed it each tick's events (frame, other actor id); it returns the actors whose contact starts."""

    def __init__(self, gap: int = CONTACT_GAP) -> None:
        self.gap = int(gap)
        self._last: dict[int, int] = {}  # other actor -> latest frame with an event

    def update(self, events: list[tuple[int, int]]) -> list[int]:
        """New contacts among ``events``, in order of their first frame (each actor at most once)."""
        return [other for _, other in self.starts(events)]

    def starts(self, events: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """(frame, other actor) of each contact that starts among ``events``: the frame is the event's own,
        which a late event carries, not the tick it was read at."""
        new: dict[int, int] = {}
        for frame, other in sorted(events):
            last = self._last.get(other)
            if (last is None or frame - last > self.gap) and other not in new:
                new[other] = frame
            self._last[other] = frame if last is None else max(last, frame)
        return [(frame, other) for other, frame in new.items()]
