"""Effects files from the page: the page runs an effects file only when the user named it on the command
line (``--effects-file``) or confirmed it in the terminal the workbench runs in; anything else is refused with a
message in the page, and its code never runs. The terminal is a real pseudo-terminal: the question is read from
its other end and answered there, as a user would type.

Each hostile file writes a marker file when its code runs: the marker's absence is the proof nothing ran."""

from __future__ import annotations

import os
import pty
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("viser")

from magcal_workbench.consent import EffectsFiles, Terminal

EXAMPLE = Path(__file__).resolve().parents[1] / "helpers" / "user_effects_example.py"
PUMP = "pump_interference"


def _click(wb, button):
    button.value = True  # what a click does: the callbacks run
    time.sleep(0.05)
    assert wb.worker.wait(120)


def _eventually(check, timeout_s=10.0) -> bool:
    """Whether ``check()`` holds within ``timeout_s`` (the page's thread applies the worker's changes soon after)."""
    end = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


def _marking(tmp_path, name="evil.py"):
    """An effects file that writes ``marker`` when its code runs: ``(file, marker)``."""
    marker = tmp_path / f"{name}.ran"
    path = tmp_path / name
    path.write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    return path, marker


class PtyTerminal:
    """A pseudo-terminal: the workbench's end (:class:`Terminal` on it) and the user's end (read the question,
    type an answer)."""

    def __init__(self):
        self.master, self.slave = pty.openpty()
        self.out = os.fdopen(os.dup(self.slave), "w", encoding="utf-8")
        self.terminal = Terminal(self.slave, self.out)

    def read_question(self, timeout_s=30.0) -> bytes:
        got, end = b"", time.monotonic() + timeout_s
        while b"within" not in got or not got.rstrip().endswith(b":"):
            ready, _, _ = select.select([self.master], [], [], max(end - time.monotonic(), 0))
            if not ready:
                raise AssertionError(f"no question in the terminal within {timeout_s} s: {got!r}")
            got += os.read(self.master, 4096)
        return got

    def type(self, text: str):
        os.write(self.master, text.encode())

    def drain(self):
        """Read what the terminal shows so far (the echo of what was typed)."""
        while select.select([self.master], [], [], 0.2)[0]:
            os.read(self.master, 4096)

    def silent(self, wait_s=0.5) -> bool:
        """Whether nothing was written to the terminal within ``wait_s``."""
        return not select.select([self.master], [], [], wait_s)[0]

    def close(self):
        self.out.close()
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def tty():
    t = PtyTerminal()
    yield t
    t.close()


def test_the_page_loads_only_the_files_of_the_command_line(bench, clean_catalogue, tmp_path):
    evil, marker = _marking(tmp_path)
    wb = bench(store=False, effects_files=[str(EXAMPLE)])  # started without a terminal (a script, a service)
    wb.panels.effects_path.value = str(evil)
    _click(wb, wb.panels.btn_load_effects)
    assert not marker.exists()
    message = wb.ctrl.message
    assert message.startswith("**Error:**") and "evil.py not loaded" in message and "--effects-file" in message
    assert str(tmp_path) not in message  # where the file lives on the server is not repeated to the page
    # a file of the command line loads (again: after the user edited it)
    wb.panels.effects_path.value = str(EXAMPLE)
    _click(wb, wb.panels.btn_load_effects)
    assert PUMP in wb.panels.effect_boxes
    # a path that leads to a named file through a symbolic link is that file; a link to another is not
    link = tmp_path / "link.py"
    link.symlink_to(evil)
    wb.panels.effects_path.value = str(link)
    _click(wb, wb.panels.btn_load_effects)
    assert not marker.exists() and "link.py not loaded" in wb.ctrl.message


def test_a_file_confirmed_in_the_terminal_loads_once_asked(bench, clean_catalogue, tmp_path, tty):
    evil, marker = _marking(tmp_path, "my\x1b[2Jeffect.py")  # a name holding a terminal's escape sequence
    wb = bench(store=False, terminal=tty.terminal)
    # the user answers no: nothing runs
    wb.panels.effects_path.value = str(evil)
    wb.panels.btn_load_effects.value = True
    question = tty.read_question()
    assert b"\x1b" not in question  # the name is shown escaped: it cannot clear or rewrite the terminal
    assert b"load the effects file" in question and b"my\\x1b[2Jeffect.py" in question
    assert "type yes there" in wb.ctrl.message  # the page says where to answer
    tty.type("no\n")
    assert wb.worker.wait(30)
    assert not marker.exists() and "not confirmed" in wb.ctrl.message and "answer was not yes" in wb.ctrl.message
    # the same file and content again: refused without a question (the page cannot flood the terminal)
    tty.drain()
    _click(wb, wb.panels.btn_load_effects)
    assert not marker.exists() and "answered no before" in wb.ctrl.message and tty.silent()
    # its content changed: asked again, the user types yes, and it runs
    evil.write_text(evil.read_text() + "# edited\n")
    wb.panels.btn_load_effects.value = True
    assert b"CHANGED" in tty.read_question()
    tty.type("yes\n")
    assert wb.worker.wait(30)
    assert marker.read_text() == "ran"
    # confirmed once, the file loads again without a question
    marker.unlink()
    tty.drain()
    _click(wb, wb.panels.btn_load_effects)
    assert marker.read_text() == "ran" and tty.silent()


def test_no_answer_in_time_refuses_and_a_yes_typed_before_the_question_does_not_count(
    bench, clean_catalogue, tmp_path, tty
):
    evil, marker = _marking(tmp_path)
    wb = bench(store=False, terminal=tty.terminal)
    wb.effects_gate.timeout_s = 1.0
    tty.type("yes\n")  # typed before anything asked
    time.sleep(0.2)
    wb.panels.effects_path.value = str(evil)
    wb.panels.btn_load_effects.value = True
    tty.read_question()
    assert wb.worker.wait(30)
    assert not marker.exists() and "no answer came" in wb.ctrl.message


def test_a_sessions_effects_files_are_refused_unless_named_or_confirmed(bench, clean_catalogue, tmp_path, tty):
    evil, marker = _marking(tmp_path)
    wb = bench()
    wb.ctrl.state.effects_files.append(str(evil))
    wb.ctrl.autosave()
    wb.stop()
    # reopened by a workbench with no terminal: refused at once, with the reason
    again = bench()
    assert again.panels.btn_session_effects.visible
    _click(again, again.panels.btn_session_effects)
    assert not marker.exists() and "evil.py not loaded" in again.ctrl.message
    again.stop()
    # with a terminal: asked, confirmed, run
    third = bench(terminal=tty.terminal)
    third.panels.btn_session_effects.value = True
    assert b"evil.py" in tty.read_question()
    tty.type("y\n")
    assert third.worker.wait(30)
    assert marker.read_text() == "ran"


def test_stopping_the_workbench_ends_a_question(bench, clean_catalogue, tmp_path, tty):
    evil, marker = _marking(tmp_path)
    wb = bench(store=False, terminal=tty.terminal)
    wb.panels.effects_path.value = str(evil)
    wb.panels.btn_load_effects.value = True
    tty.read_question()
    t0 = time.monotonic()
    wb.stop()
    assert time.monotonic() - t0 < 10 and not marker.exists()


def test_the_terminal_is_the_foreground_standard_input_only():
    """:meth:`Terminal.of_stdin`: a terminal in whose foreground the workbench runs; not a pipe, not a background
    job (which the terminal would stop when it reads)."""
    code = "from magcal_workbench.consent import Terminal; print('TERMINAL' if Terminal.of_stdin() else 'NONE')"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    piped = subprocess.run(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, capture_output=True, env=env, timeout=60
    )
    assert piped.stdout.strip() == b"NONE"

    def under_pty(background: bool) -> bytes:
        pid, fd = pty.fork()
        if pid == 0:  # the child leads a session whose controlling terminal is the pty, in its foreground
            if background:  # a job of that session in another process group: the shell's "&"
                job = os.fork()
                if job == 0:
                    os.setpgid(0, 0)
                    os.execve(sys.executable, [sys.executable, "-c", code], env)
                os.waitpid(job, 0)
                os._exit(0)
            os.execve(sys.executable, [sys.executable, "-c", code], env)
        out = b""
        end = time.monotonic() + 60
        while time.monotonic() < end:
            if select.select([fd], [], [], 1.0)[0]:
                try:
                    chunk = os.read(fd, 1024)
                except OSError:
                    break
                if not chunk:
                    break
                out += chunk
        os.waitpid(pid, 0)
        os.close(fd)
        return out

    assert b"TERMINAL" in under_pty(background=False)
    assert b"NONE" in under_pty(background=True)


def test_an_empty_path_is_a_message():
    from magcal.core.errors import MagcalError

    with pytest.raises(MagcalError, match="type the path"):
        EffectsFiles().permit("  ")


def test_a_pipe_or_a_folder_is_refused_before_anything_opens_it(bench, clean_catalogue, tmp_path, tty):
    """A FIFO named as an effects file would block the reader for ever (item 9): the page refuses it, a
    folder and a missing file at once, without asking the terminal."""
    fifo = tmp_path / "pipe.py"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.py"
    folder.mkdir()
    wb = bench(store=False, terminal=tty.terminal, effects_files=[str(fifo)])
    for path, says in ((fifo, "not a regular file"), (folder, "not a regular file"), (tmp_path / "no.py", "no such")):
        wb.panels.effects_path.value = str(path)
        _click(wb, wb.panels.btn_load_effects)
        assert says in wb.ctrl.message and path.name in wb.ctrl.message
    assert tty.silent()


# --- the consent is bound to the bytes that run ------------------------------------------------------------------


def _flipping(link, targets, stop):
    """Point ``link`` at each of ``targets`` in turn, as fast as it can, until ``stop`` is set (the attack: a link
    moved between the check and the run)."""
    import random

    spare = link.with_name(link.name + ".next")
    pace = random.Random(7)
    k = 0
    while not stop.is_set():
        k += 1
        spare.unlink(missing_ok=True)
        spare.symlink_to(targets[k % len(targets)])
        os.replace(spare, link)  # atomic: the link always exists and names one of the two
        time.sleep(pace.uniform(0.0, 2e-4))  # an uneven pace: the flips fall at every point of a load


@pytest.mark.parametrize("each", [10])
def test_a_link_flipped_while_the_file_loads_never_runs_the_other_file(clean_catalogue, tmp_path, each):
    """Only ``good.py`` is named; ``link.py`` flips between it and ``evil.py`` in a thread while the page's rule
    (:meth:`EffectsFiles.permit`) and the load run, until each target was met ``each`` times: the good file loads,
    the evil one never runs."""
    import threading

    from magcal.core.errors import MagcalError
    from magcal.model import plugins

    good = tmp_path / "good.py"
    good.write_text(EXAMPLE.read_text())
    evil, marker = _marking(tmp_path)
    link = tmp_path / "link.py"
    link.symlink_to(good)
    gate = EffectsFiles(named=[str(good)])  # no terminal: anything but good.py is refused
    stop = threading.Event()
    flipper = threading.Thread(target=_flipping, args=(link, [good, evil], stop), daemon=True)
    flipper.start()
    ran = refused = tries = 0
    try:
        while (ran < each or refused < each) and tries < 150 * each:
            tries += 1
            try:
                source = gate.permit(str(link))
            except MagcalError:
                refused += 1
                continue
            assert plugins.load_effects_file(source) == [PUMP]
            ran += 1
    finally:
        stop.set()
        flipper.join(10)
    assert not marker.exists()
    assert ran >= each and refused >= each  # the race was on: both targets were met


def test_the_bytes_checked_are_the_bytes_that_run(clean_catalogue, tmp_path):
    """A file replaced after it was read and confirmed: what runs is what was read (the old content)."""
    from magcal.model import plugins

    good = tmp_path / "good.py"
    good.write_text(EXAMPLE.read_text())
    gate = EffectsFiles(named=[str(good)])
    source = gate.permit(str(good))
    evil, marker = _marking(tmp_path)
    os.replace(evil, good)  # good.py now holds the other code
    assert plugins.load_effects_file(source) == [PUMP]
    assert not marker.exists()


def test_a_folder_swapped_for_a_link_after_the_check_is_refused(clean_catalogue, tmp_path, monkeypatch):
    """The path is resolved once, then opened a component at a time without following a link: a folder on the way
    that becomes a link at the worst moment (after the path was resolved) is refused, nothing runs."""
    from magcal.core.errors import MagcalError
    from magcal.model import plugins

    (tmp_path / "mine").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "mine" / "fx.py").write_text(EXAMPLE.read_text())
    (tmp_path / "other" / "fx.py").write_text(f"open({str(tmp_path / 'ran')!r}, 'w')\n")
    resolve = os.path.realpath

    def resolve_then_swap(path):
        real = resolve(path)
        os.rename(tmp_path / "mine", tmp_path / "mine.old")
        os.symlink(tmp_path / "other", tmp_path / "mine")
        return real

    monkeypatch.setattr(plugins.os.path, "realpath", resolve_then_swap)
    with pytest.raises(MagcalError, match="replaced while it was opened"):
        plugins.load_effects_file(tmp_path / "mine" / "fx.py")
    assert not (tmp_path / "ran").exists()


def test_with_a_terminal_the_flipped_link_is_asked_about_and_a_no_holds(clean_catalogue, tmp_path, tty):
    """The same race with a terminal whose user answers no to every question: the evil file never runs, and it is
    asked about once (its content answered no is not asked again)."""
    import threading

    from magcal.core.errors import MagcalError
    from magcal.model import plugins

    good = tmp_path / "good.py"
    good.write_text(EXAMPLE.read_text())
    evil, marker = _marking(tmp_path)
    link = tmp_path / "link.py"
    link.symlink_to(good)
    gate = EffectsFiles(named=[str(good)], terminal=tty.terminal, timeout_s=20.0)
    stop = threading.Event()
    questions = []

    def user():  # answers no to every question
        while not stop.is_set():
            try:
                questions.append(tty.read_question(timeout_s=0.5))
            except AssertionError:
                continue
            tty.type("no\n")

    threads = [threading.Thread(target=f, daemon=True) for f in (user,)]
    threads.append(threading.Thread(target=_flipping, args=(link, [good, evil], stop), daemon=True))
    for t in threads:
        t.start()
    try:
        for _ in range(60):
            try:
                plugins.load_effects_file(gate.permit(str(link)))
            except MagcalError:
                pass
    finally:
        stop.set()
        for t in threads:
            t.join(10)
    assert not marker.exists()
    assert len(questions) == 1 and b"evil.py" in questions[0]


def test_a_confirmed_file_whose_content_changed_is_asked_again(bench, clean_catalogue, tmp_path, tty):
    path = tmp_path / "mine.py"
    path.write_text(EXAMPLE.read_text())
    wb = bench(store=False, terminal=tty.terminal)
    wb.panels.effects_path.value = str(path)
    wb.panels.btn_load_effects.value = True
    first = tty.read_question()
    assert b"SHA-256" in first and b"CHANGED" not in first
    tty.type("yes\n")
    assert wb.worker.wait(30) and PUMP in wb.panels.effect_boxes
    tty.drain()
    _click(wb, wb.panels.btn_load_effects)  # the same content: no question
    assert tty.silent() and "loaded" in wb.ctrl.message
    marker = tmp_path / "changed.ran"
    path.write_text(EXAMPLE.read_text() + f"\nopen({str(marker)!r}, 'w')\n")
    wb.panels.btn_load_effects.value = True
    assert b"CHANGED" in tty.read_question()
    tty.type("no\n")
    assert wb.worker.wait(30)
    assert not marker.exists() and "not confirmed" in wb.ctrl.message


def test_a_name_with_look_alike_characters_is_shown_escaped_and_marked(bench, clean_catalogue, tmp_path, tty):
    """``gооd.py`` with two Cyrillic ``о``: the terminal shows them as escapes, marked with the letter they look
    like, and so does the page; the raw characters never reach the terminal."""
    evil, marker = _marking(tmp_path, "g\u043e\u043ed.py")
    wb = bench(store=False, terminal=tty.terminal)
    wb.panels.effects_path.value = str(evil)
    wb.panels.btn_load_effects.value = True
    question = tty.read_question()
    assert "\u043e".encode() not in question
    assert b"g\\u043e\\u043ed.py" in question
    assert b"CYRILLIC SMALL LETTER O, looks like 'o'" in question
    assert "u043e" in wb.ctrl.message and "CYRILLIC SMALL LETTER O" in wb.ctrl.message
    # the status line says where to answer
    assert _eventually(lambda: "waiting for your answer" in wb.panels.progress_text.content)
    tty.type("no\n")
    assert wb.worker.wait(30)
    assert not marker.exists()


@pytest.mark.parametrize("answer", ["yes", "no"])
def test_a_session_naming_one_file_100_ways_asks_once(bench, clean_catalogue, tmp_path, tty, answer):
    """A session lists one effects file under 100 names (``./``, ``..``, doubled slashes, links): one question,
    and on yes the file runs once."""
    folder = tmp_path / "fx"
    folder.mkdir()
    marker = tmp_path / "runs.txt"
    path = folder / "mine.py"
    future = "from __future__ import annotations\n"  # the count comes first: a run that fails later still counts
    path.write_text(EXAMPLE.read_text().replace(future, future + f"open({str(marker)!r}, 'a').write('ran\\n')\n", 1))
    names = []
    for k in range(100):
        kind = k % 4
        if kind == 0:
            link = tmp_path / f"link{k}.py"
            link.symlink_to(path)
            names.append(str(link))
        elif kind == 1:
            names.append(str(folder) + "/." * (k // 4 + 1) + "/mine.py")
        elif kind == 2:
            names.append(str(folder) + f"/../fx{'/' * (k // 4 + 1)}mine.py")
        else:
            names.append(str(folder) + "/../fx/." * (k // 4 + 1) + "/mine.py")
    assert len(set(names)) == 100
    wb = bench(store=False, terminal=tty.terminal)
    wb.ctrl.state.effects_files.extend(names)
    wb.panels.btn_session_effects.value = True
    tty.read_question()
    assert _eventually(lambda: "waiting for your answer" in wb.panels.progress_text.content)
    tty.type(answer + "\n")
    assert wb.worker.wait(60)
    tty.drain()
    assert tty.silent(1.0)  # no second question
    if answer == "yes":
        assert marker.read_text() == "ran\n" and PUMP in wb.panels.effect_boxes
        assert "99 more path(s)" in wb.ctrl.message and not wb.ctrl.pending_effects_files()
    else:
        assert not marker.exists() and "not confirmed" in wb.ctrl.message
