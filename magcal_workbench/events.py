"""What changed, as the controller tells the page: one enum, so that a kind the page handles is one that is sent.

The controller (:class:`magcal_workbench.controller.Controller`) calls its listeners with a :class:`Change` through
:meth:`Controller.emit <magcal_workbench.controller.Controller.emit>`, the one way a change is sent (the model sessions
send theirs through it too; an unknown kind is refused there, not lost); the workbench routes it to the scene, the
panels, the vehicle view and the added panels (``Workbench._changed``), each of which redraws only for the kinds it
names.
A :class:`~enum.StrEnum`: a member equals its text, so ``"result" in kinds`` still holds.
``tests/workbench/test_workbench_events.py`` checks that every kind sent is a member, every member is sent, and every kind a
handler names is a member.
"""

from __future__ import annotations

from enum import StrEnum


class Change(StrEnum):
    """A kind of change (the controller's event)."""

    #: The page's message line changed.
    MESSAGE = "message"
    #: A setting of the session (robust loss, reference, the vector loop's options) changed.
    SETTINGS = "settings"
    #: A new calibration: the corrected clouds, the status, the plots.
    RESULT = "result"
    #: A long step's progress (a search's iterations, a diagnosis's refits).
    PROGRESS = "progress"
    #: The diagnosis was made, or no longer applies.
    DIAGNOSIS = "diagnosis"
    #: The model or its history (steps, held-out figures) changed.
    MODEL = "model"
    #: The catalogue of effects grew (an effects file was loaded).
    EFFECTS = "effects"
    #: Samples were rejected or restored.
    SELECTION = "selection"
    #: The inspected sample changed.
    INSPECT = "inspect"
    #: An autosave failed, or succeeded again.
    SAVED = "saved"
    #: The vector fit or its reference changed.
    VECTOR = "vector"
    #: The gravity fit (a compass beside an accelerometer) changed.
    GRAVITY = "gravity"
    #: The compensation (a scalar magnetometer beside a fluxgate: Tolles-Lawson and beyond) changed.
    COMPENSATION = "compensation"
    #: A new record was opened: everything is redrawn (sent by the workbench's redraw, not by the controller).
    DATA = "data"
