"""Bad inputs from the workbench's page: the effects-file consent raced and flooded, bad numbers in the widgets.

Run: ``PYTHONPATH=$PWD python benchmarks/page_bad_inputs.py [--loads 200]`` (about 40 s). Prints three tables, ours
against the old behaviour run the old way here:

* **a link flipped between the check and the run**: only ``good.py`` is allowed (by the command line, or by a
  terminal whose user answers no to everything); ``link.py`` flips between it and ``evil.py`` in a thread while
  the page loads it ``--loads`` times. Ours: :meth:`EffectsFiles.permit` reads the file once and the load runs
  those bytes. Old: the resolved path is checked, then the file is imported again by its name (the order the
  audit raced). Counted: how often evil.py's code ran, and the questions asked.
* **one file named 100 ways by a session** (``./``, ``..``, doubled slashes, links), the terminal answering no,
  then yes: questions asked and how often the file's code ran. Old: one question per path, every path loaded.
* **bad values for the Port box** (the live source *Send to vehicle* uses), as a browser could send them. Old:
  what viser's own handler does with the value (it casts it to the widget's type, ``int``). Ours: the screen
  before viser (:meth:`magcal_workbench.checks.PageValues.screen`) and the message the page gets.

``benchmarks/notes/page_bad_inputs.md`` has the tables; the rows join the command line's
(``benchmarks/bad_inputs.py``).
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import threading
import time
from pathlib import Path

from magcal.core.errors import MagcalError
from magcal.model import plugins
from magcal.model.terms import EFFECTS
from magcal_workbench.consent import EffectsFiles

EXAMPLE = Path(__file__).resolve().parents[1] / "tests" / "user_effects_example.py"


class Answering:
    """A terminal whose user answers ``answer`` to every question at once; counts the questions."""

    def __init__(self, answer: str):
        self.answer, self.asked = answer, 0

    def ask(self, question, timeout_s, cancel):
        self.asked += 1
        return self.answer


class OldGate:
    """The old rule: the resolved path checked against those named or confirmed, a no not remembered."""

    def __init__(self, named, terminal):
        self.allowed = {os.path.realpath(p) for p in named}
        self.terminal = terminal

    def permit(self, path) -> str:
        key = os.path.realpath(path)
        if key in self.allowed:
            return path
        if self.terminal is not None and self.terminal.ask("load?", 1, None) == "yes":
            self.allowed.add(key)
            return path
        raise MagcalError("not confirmed")


def _files(folder: Path):
    good = folder / "good.py"
    good.write_text(EXAMPLE.read_text())
    runs = folder / "evil_runs.txt"
    evil = folder / "evil.py"
    evil.write_text(f"open({str(runs)!r}, 'a').write('x')\n")
    return good, evil, runs


def _counting(runs: Path) -> str:
    """The example effects file with a first statement that counts its runs in ``runs`` (a run that fails later,
    at a name already taken, still ran the file's code)."""
    future = "from __future__ import annotations\n"
    return EXAMPLE.read_text().replace(future, future + f"open({str(runs)!r}, 'a').write('x')\n", 1)


def _count(path: Path) -> int:
    return len(path.read_text()) if path.exists() else 0


def _flip(link: Path, targets, stop: threading.Event) -> None:
    spare, pace, k = link.with_name("link.next"), random.Random(7), 0
    while not stop.is_set():
        k += 1
        spare.unlink(missing_ok=True)
        spare.symlink_to(targets[k % 2])
        os.replace(spare, link)
        time.sleep(pace.uniform(0.0, 2e-4))


def race(loads: int, answer: str | None, ours: bool) -> tuple[int, int, int]:
    """``(evil runs, good loads, questions)`` of ``loads`` loads of a flipping link (``answer``: the terminal's
    user's answer to every question, None: no terminal)."""
    before = dict(EFFECTS)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        good, evil, runs = _files(folder)
        link = folder / "link.py"
        link.symlink_to(good)
        terminal = Answering(answer) if answer is not None else None
        gate = EffectsFiles([str(good)], terminal) if ours else OldGate([str(good)], terminal)  # type: ignore[arg-type]
        stop = threading.Event()
        flipper = threading.Thread(target=_flip, args=(link, [good, evil], stop), daemon=True)
        flipper.start()
        loaded = 0
        try:
            for _ in range(loads):
                try:
                    allowed = gate.permit(str(link))
                    plugins.load_effects_file(allowed)  # ours: the bytes read; old: the path, imported again
                    loaded += 1
                except MagcalError:
                    pass
        finally:
            stop.set()
            flipper.join(10)
        _forget(before)
        return _count(runs), loaded, terminal.asked if terminal is not None else 0


def _forget(before: dict) -> None:
    """Put the catalogue back as it was (the runs load the same effect from many paths)."""
    EFFECTS.clear()
    EFFECTS.update(before)
    for table in (plugins._ORIGINS, plugins._SOURCES):
        for name in [n for n in table if n not in before]:
            del table[name]
    plugins._USER_FILES.clear()


def hundred_ways(answer: str, ours: bool) -> tuple[int, int]:
    """``(questions, runs of the file's code)`` for a session naming one file 100 ways."""
    before = dict(EFFECTS)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "fx"
        folder.mkdir()
        runs = Path(tmp) / "runs.txt"
        path = folder / "mine.py"
        path.write_text(_counting(runs))
        names = []
        for k in range(100):
            if k % 2:
                link = Path(tmp) / f"link{k}.py"
                link.symlink_to(path)
                names.append(str(link))
            else:
                names.append(str(folder) + "/." * (k // 2 + 1) + "/mine.py")
        terminal = Answering(answer)
        if ours:
            gate = EffectsFiles((), terminal)  # type: ignore[arg-type]
            got = gate.permit_all(names)
            done = set()
            for source in got.values():
                if isinstance(source, plugins.EffectsSource) and (source.real, source.sha256) not in done:
                    done.add((source.real, source.sha256))
                    plugins.load_effects_file(source)
        else:
            old = OldGate((), terminal)
            for name in names:
                try:
                    plugins.load_effects_file(old.permit(name))
                except MagcalError:
                    pass
        _forget(before)
        return terminal.asked, _count(runs)


PORT_VALUES = [float("nan"), float("inf"), float("-inf"), [14550, 1], 14551.5, "14550", True, 80, 70000]


def port_values() -> list[tuple[str, str, str]]:
    """``(value, old, ours)`` for each bad Port value: what viser's cast made of it, and our screen's verdict."""
    import magcal
    from magcal.data import io as mio
    from magcal_workbench.app import Workbench

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "data.csv"
        mio.write_csv(path, magcal.simulate_timeseries("chi2017", n_samples=200, seed=5, rate_hz=2.0))
        wb = Workbench(mio.read_csv(path), host="127.0.0.1", port=0, store=None, content=path.read_bytes())
        try:
            port = wb.panels.live_port
            for value in PORT_VALUES:
                try:
                    cast = type(port.value)(value)  # what viser's handler does first, in its event loop
                    old = f"port set to {cast!r}" + (", silently" if cast != value else "")
                    if not 1024 <= cast <= 65535:
                        old += " (refused later by the Start button)"
                except (TypeError, ValueError, OverflowError) as exc:
                    old = f"{type(exc).__name__} in viser's event loop: a traceback, nothing in the page"
                why = wb.values.screen(port, {"value": value})
                ours = "accepted" if why is None else f"refused: {why}"
                rows.append((repr(value), old, ours))
        finally:
            wb.stop()
    return rows


def _slashed(counts) -> str:
    return " / ".join(str(c) for c in counts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--loads", type=int, default=200, help="loads of the flipping link per row")
    args = parser.parse_args()
    print(f"a link flipped between good.py and evil.py, {args.loads} loads (evil runs / good loads / questions)")
    print(f"{'allowed':34s} {'old':>16s} {'ours':>16s}")
    bad = 0
    for label, answer in (("good.py on the command line", None), ("... and a terminal answering no", "no")):
        old = race(args.loads, answer, ours=False)
        new = race(args.loads, answer, ours=True)
        bad += new[0]
        print(f"{label:34s} {_slashed(old):>16s} {_slashed(new):>16s}")
    print("\none file named 100 ways by a session (questions / runs of its code)")
    print(f"{'answer':34s} {'old':>16s} {'ours':>16s}")
    for answer in ("no", "yes"):
        old = hundred_ways(answer, ours=False)
        new = hundred_ways(answer, ours=True)
        bad += new[0] > 1 or new[1] > (answer == "yes")
        print(f"{answer:34s} {_slashed(old):>16s} {_slashed(new):>16s}")
    print("\nbad values for the Port box (live source, Send to vehicle)")
    rows = port_values()
    for value, old, ours in rows:
        print(f"{value:14s} old: {old}\n{'':14s} ours: {ours}")
    bad += sum(not ours.startswith("refused") for _, _, ours in rows)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
