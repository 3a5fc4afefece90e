"""The Lessons tab, a panel of the panel recipe (:mod:`magcal_workbench.panelkit`): choose a lesson, open it, check
the model against its answer, show the answer, with the handlers of its buttons beside them.

:class:`LessonsTab` is built at its place by :class:`~magcal_workbench.panels.Panels` (``build(panels, gui)``) and
offers ``do_open_lesson``, ``do_check_lesson`` and ``do_show_answer`` to the page's widgets like every part's
:func:`~magcal_workbench.actions.action`. The lessons themselves (their data, guide and answer, the check) are
:mod:`magcal_workbench.lessons`'.
"""

from __future__ import annotations

from magcal.core.errors import MagcalError

from .actions import action
from .dataio import load_dataset
from .lessons import Lesson, lesson_or_error, lesson_titles, list_lessons


class LessonsTab:
    """The Lessons tab's widgets and their handlers.

    Parameters
    ----------
    ctrl : callable
        ``ctrl()``: the open data's :class:`~magcal_workbench.controller.Controller`.
    gravity : callable
        ``gravity()``: the :class:`~magcal_workbench.gravitypage.GravityPage` (a gravity lesson is judged on its
        model).
    ui : magcal_workbench.uiqueue.UiQueue
        The page's thread: the opened lesson's guide is shown through it.
    load : callable
        ``load(dataset, content, name, resume=True, lesson=slug)``: opens the lesson's data
        (:meth:`magcal_workbench.app.Workbench.load`).
    say_after_load : callable
        ``say_after_load(text)``: says the lesson opened (:meth:`magcal_workbench.app.Workbench.say_after_load`).
    """

    #: The tab it fills.
    tab = "Lessons"

    def __init__(self, *, ctrl, gravity, ui, load, say_after_load):
        self._ctrl, self._gravity = ctrl, gravity
        self.ui, self.load, self.say_after_load = ui, load, say_after_load
        self.values = None

    def attach(self, panels) -> None:
        """Built already at its place, else into its tab now."""
        if self.values is None:
            with panels.tab(self.tab):
                self.build(panels, panels.gui)

    def build(self, panels, gui) -> None:
        """Make the widgets (in the tab being built)."""
        self.values = panels.values
        on = panels.on
        opts = lesson_titles()
        gui.add_markdown(
            "Each lesson hides a physical effect in its data. Fit, diagnose, add what you think "
            "is missing, and check. The answer stays hidden until you ask."
        )
        self.lesson_choice = panels.w.dropdown(
            "Lesson",
            opts,
            allowed=lesson_titles,
            initial_value=opts[0],
            hint="; ".join(f"{l.title} (--lesson {l.slug})" for l in list_lessons()),
        )
        self.btn_lesson = panels.button("Open the lesson", on.do_open_lesson, engine=True)
        self.lesson_guide = gui.add_markdown("")
        self.btn_check = panels.button("Check my model", on.do_check_lesson)
        self.btn_answer = panels.button("Show the answer", on.do_show_answer)
        self.lesson_feedback = gui.add_markdown("")
        panels.tab_panels.append(self)

    def refresh(self, kinds) -> None:
        """Nothing follows the controller's events: the handlers write the guide and the feedback."""

    def show_guide(self, lesson: Lesson) -> None:
        """The lesson's title and guide in the tab."""
        self.lesson_guide.content = f"### {lesson.title}\n\n{lesson.guide()}"

    def current(self) -> Lesson:
        """The lesson open now, or a :class:`~magcal.core.errors.MagcalError` the page shows."""
        state = self._ctrl().state
        if not state.lesson:
            raise MagcalError("open a lesson first (Lessons tab)")
        return lesson_or_error(state.lesson)

    # --- page actions --------------------------------------------------------------------------------------
    @action
    def do_open_lesson(self, event):
        """Open the chosen lesson's data (its saved session when there is one) and show its guide."""
        lesson = lesson_or_error(self.values.check(self.lesson_choice))
        slug = lesson.slug

        def job():
            ds, _ = load_dataset(lesson.data_path, f"lesson {slug}")
            content = lesson.data_path.read_bytes()
            self.load(ds, content, f"lesson-{slug}.csv", resume=True, lesson=slug)
            revealed = self._ctrl().state.answer_revealed

            def show():
                self.show_guide(lesson)
                self.lesson_feedback.content = lesson.answer_markdown() if revealed else ""

            self.ui.post(show)
            self.say_after_load(f"lesson **{lesson.title}** opened")

        self._ctrl().run_job("open lesson", job)

    @action
    def do_check_lesson(self, event):
        """Compare the model (the gravity model's for a gravity lesson, the compensation's for a compensation
        lesson) with the answer, without revealing it."""
        ctrl = self._ctrl()
        lesson = self.current()
        if lesson.answer().get("model") == "compensation":
            found = ctrl.compensation.lesson_findings()
        elif lesson.judged_on == "gravity":
            found = self._gravity().model.lesson_findings()
        else:
            found = ctrl.vector.lesson_findings()
        result = lesson.check(ctrl.state.effects, found)
        self.lesson_feedback.content = result["message"]
        ctrl.say(result["message"])

    @action
    def do_show_answer(self, event):
        """Reveal the answer (remembered by the session)."""
        lesson = self.current()
        ctrl = self._ctrl()
        ctrl.state.answer_revealed = True
        ctrl.state.touch()
        ctrl.autosave()
        self.lesson_feedback.content = lesson.answer_markdown()
