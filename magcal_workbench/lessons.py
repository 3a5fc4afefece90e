"""Lessons: datasets that each hide a physical effect, with a short guide; the answer stays hidden until asked.

A lesson is a folder under ``assets/lessons/``::

    <slug>/lesson.json   {"title", "order", "data": "data.csv", "guide": "guide.md",
                          "answer": {"effects": ["temperature_bias:2", ...], "explanation": "..."}}
                         a lesson of the vector model adds to its answer "mounting": the right angle
                         (firmware name) per sensor, "mounting_off_deg" and "mounting_tolerance_deg": solved by a
                         vector fit that finds them; "model": "vector" judges the vector model's effects (the
                         loop on a vehicle) instead of the total-field model's; "model": "compensation" judges
                         the compensation's terms beyond Tolles-Lawson, and with "true_fom_nT" (and "fom_ratio",
                         1.2 by default) its FOM within that ratio of the true compensation's
    <slug>/guide.md      what to look at (never names the answer)
    <slug>/data.csv      the data (made by ``assets/make_assets.py`` from the engine's simulator)

:meth:`Lesson.check` compares the user's model with the answer without revealing it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from magcal.core.errors import MagcalError

from .markup import clean_text, safe_text


def _assets_folder() -> Path:
    """The demo data and lessons: ``assets/`` of a source checkout, else the copy a wheel installs as
    ``magcal_workbench/assets`` (see ``pyproject.toml``)."""
    here = Path(__file__).resolve().parent
    for folder in (here.parent / "assets", here / "assets"):
        if (folder / "demo.csv").is_file():
            return folder
    return here.parent / "assets"


#: The asset folder (demo data and lessons).
ASSETS = _assets_folder()
LESSONS = ASSETS / "lessons"
DEMO = ASSETS / "demo.csv"


@dataclass
class Lesson:
    """One lesson folder."""

    slug: str
    folder: Path
    title: str
    order: int

    @property
    def data_path(self) -> Path:
        """The lesson's data file: a plain file name inside the lesson's folder (no path, no ``..``)."""
        name = self._doc().get("data", "data.csv")
        if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
            raise MagcalError(
                f"{self.folder / 'lesson.json'}: 'data' must be a file name in the lesson's folder, got {name!r}"
            )
        return self.folder / name

    def guide(self) -> str:
        """The guide (markdown), with no answer in it."""
        return (self.folder / self._doc().get("guide", "guide.md")).read_text(encoding="utf-8")

    def answer(self) -> dict:
        """``{"effects": [labels], "explanation": str}`` (and, for a lesson of the vector model, ``mounting``: the
        right angle per sensor, ``mounting_off_deg``, ``mounting_tolerance_deg``) — show only when the user asks."""
        ans = self._doc().get("answer", {})
        out = {"effects": list(ans.get("effects", [])), "explanation": ans.get("explanation", "")}
        if ans.get("model") in ("vector", "compensation"):
            out["model"] = ans["model"]
        if ans.get("true_fom_nT") is not None:
            out["true_fom_nT"] = float(ans["true_fom_nT"])
            out["fom_ratio"] = float(ans.get("fom_ratio", 1.2))
        if ans.get("mounting"):
            out["mounting"] = list(ans["mounting"])
            out["mounting_off_deg"] = float(ans.get("mounting_off_deg", 0.0))
            out["mounting_tolerance_deg"] = float(ans.get("mounting_tolerance_deg", 0.5))
        return out

    @property
    def judged_on(self) -> str:
        """The fit a lesson with a mounting is judged on: ``vector`` (default) or ``gravity`` (the lesson's
        ``"fit"``)."""
        return "gravity" if self._doc().get("fit") == "gravity" else "vector"

    def answer_markdown(self) -> str:
        ans = self.answer()
        terms = ", ".join(f"`{e}`" for e in ans["effects"]) or "no effect beyond the base terms"
        if ans.get("mounting"):
            terms += f"; the {self.judged_on} fit's mounting " + ", ".join(f"`{m}`" for m in ans["mounting"])
            terms += f", {ans['mounting_off_deg']:g} deg off the right angle"
        return f"**Answer:** {terms}\n\n{ans['explanation']}"

    def check(self, effects, vector=None) -> dict:
        """Compare the model's effect labels (and, for a lesson of the vector model, the vector fit's mounting) with
        the answer.

        Parameters
        ----------
        effects : sequence of str
            The model's effect labels.
        vector : dict, optional
            The vector fit's findings (:meth:`magcal_workbench.vectormodel.VectorModel.lesson_findings`):
            ``mounting`` (right angle per sensor), ``angle_off_deg`` and ``effects`` (the vector model's, which a
            lesson whose answer says ``"model": "vector"`` judges instead of ``effects``); None before a vector fit.

        Returns
        -------
        dict
            ``found`` (answer labels the model covers), ``missing`` count (not names: the answer stays
            hidden), ``extra`` (model labels not in the answer), ``solved`` (all found, nothing extra) and a
            one-line ``message``.
        """
        answer = self.answer()
        wanted = answer["effects"]
        judged_model = answer.get("model")  # "vector" or "compensation": that model's effects are judged
        on_vector = judged_model is not None
        if on_vector:
            effects = (vector or {}).get("effects", [])
        have = [e.strip() for e in effects]
        found, covered = [], set()
        for w in wanted:
            name = w.partition(":")[0]
            match = next((h for h in have if h == w or h == name), None)
            if match is not None:
                found.append(w)
                covered.add(match)
        extra = [h for h in have if h not in covered]
        missing = len(wanted) - len(found)
        mounting = self._check_mounting(vector)
        if mounting is not None:  # a lesson of the vector model: the mounting is one more thing to find
            wanted = wanted + ["mounting"]
            if mounting == "found":
                found.append("mounting")
            else:
                missing += 1
        solved = missing == 0 and not extra
        fit = self.judged_on
        fom_short = _fom_short(answer, vector) if solved else ""
        if on_vector and not vector:
            solved = False
            message = (
                f"Not yet: this lesson is judged on the {judged_model} model (Model tab: Diagnose and Add work on "
                f"the {judged_model} fit of these data), which has not been fitted yet."
            )
        elif fom_short:
            solved = False
            message = fom_short
        elif mounting == "no fit":
            message = (
                f"Not yet: this lesson is judged on the {fit} fit (Calibrate tab, Run the {fit} fit), which has not "
                "been run on these data."
                + (f" Your model also holds terms not hidden here: {_labels(extra)}." if extra else "")
            )
        elif mounting == "wrong":
            message = (
                "The vector fit ran, but the mounting it found is not the one hidden in the data: check the reference "
                "field (where and when was the vehicle flown?) and the samples kept."
                if fit == "vector"
                else "The gravity fit ran, but the mounting it found is not the one hidden in the data: check the "
                "samples kept (the still ones measure gravity)."
            )
        elif solved:
            message = (
                f"Solved: the {fit} fit found the mounting the "
                + ("vehicle" if fit == "vector" else "board")
                + " was built with."
                if mounting
                else f"Solved: your {f'{judged_model} ' if judged_model else ''}model holds exactly the hidden effect(s)."
            )
        elif missing == 0:
            message = f"All hidden effects are in, plus {len(extra)} more than needed: {_labels(extra)}."
        else:
            message = (
                f"{len(found)} of {len(wanted)} hidden effect(s) found"
                + (f"; not hidden here: {_labels(extra)}" if extra else "")
                + ". Keep looking."
            )
        return {"found": found, "missing": missing, "extra": extra, "solved": solved, "message": message}

    def _check_mounting(self, vector) -> str | None:
        """None (not a lesson of the vector model), ``no fit``, ``wrong`` or ``found``."""
        ans = self.answer()
        if not ans.get("mounting"):
            return None
        if not vector:
            return "no fit"
        names, offs = list(vector.get("mounting", [])), list(vector.get("angle_off_deg", []))
        if len(names) != len(ans["mounting"]) or len(offs) != len(names):
            return "wrong"
        ok = all(
            n == want and abs(off - ans["mounting_off_deg"]) <= ans["mounting_tolerance_deg"]
            for n, want, off in zip(names, ans["mounting"], offs)
        )
        return "found" if ok else "wrong"

    def _doc(self) -> dict:
        with open(self.folder / "lesson.json", encoding="utf-8") as fh:
            return json.load(fh)


def _fom_short(answer: dict, findings) -> str:
    """Why a compensation holding the hidden terms is not yet solved: its FOM (nT) above ``fom_ratio`` times the
    true compensation's (``true_fom_nT``); empty when within it or when the lesson names no FOM."""
    true = answer.get("true_fom_nT")
    fom = (findings or {}).get("fom_nT")
    if true is None or fom is None or fom <= answer["fom_ratio"] * true:
        return ""
    return (
        f"The terms are right, but the FOM is {fom:.3g} nT, more than {answer['fom_ratio']:g}x the true "
        f"compensation's {true:.3g} nT: check the samples kept (every maneuver should be in the fit)."
    )


def _labels(labels) -> str:
    """The user's effect labels for the (markdown) message, escaped: they come from the session."""
    return ", ".join(safe_text(label, 80) for label in labels)


def list_lessons(root=None) -> list[Lesson]:
    """Lessons under ``root`` (default :data:`LESSONS`), in their ``order``."""
    root = Path(root) if root is not None else LESSONS
    out: list = []
    if not root.is_dir():
        return out
    for folder in sorted(root.iterdir()):
        meta = folder / "lesson.json"
        if not meta.is_file():
            continue
        with open(meta, encoding="utf-8") as fh:
            doc = json.load(fh)
        out.append(Lesson(folder.name, folder, doc.get("title", folder.name), int(doc.get("order", 99))))
    out.sort(key=lambda l: (l.order, l.slug))
    return out


def get_lesson(slug: str, root=None) -> Lesson:
    for lesson in list_lessons(root):
        if lesson.slug == slug:
            return lesson
    raise KeyError(f"no lesson {slug!r}")


def lesson_or_error(choice) -> Lesson:
    """The lesson of a slug or a title (what the Lessons tab lists), or a :class:`MagcalError` the page can show."""
    for lesson in list_lessons():
        if choice in (lesson.slug, lesson.title):
            return lesson
    raise MagcalError(f"no lesson {clean_text(repr(choice), 80)}; choose one in the Lessons tab")


def lesson_slugs() -> tuple:
    """The lessons' slugs (``-`` when there is none): what ``--lesson`` takes."""
    return tuple(lesson.slug for lesson in list_lessons()) or ("-",)


def lesson_titles() -> tuple:
    """The Lesson choices the page offers: the lessons' titles, in their order (``-`` when there is none)."""
    return tuple(lesson.title for lesson in list_lessons()) or ("-",)
