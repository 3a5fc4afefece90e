"""Untrusted text made safe for the page.

viser renders every markdown widget with raw HTML switched on (its client parses ``<img onerror=...>`` inside
markdown as HTML, without sanitising) and draws :meth:`~viser.GuiApi.add_html` verbatim. Text the workbench did
not write itself -- the contents and names of uploaded files (echoed in the reader's messages), fields of a
session file, names and descriptions of a user's effects, messages of exceptions -- must therefore pass through
:func:`safe_text` (in running markdown) or :func:`safe_code` (as an inline code span) before it joins a markdown
string. Text of plain-text widgets (notifications, hints, labels: React escapes them) only needs
:func:`clean_text` so that a 3 MB header does not become a 3 MB toast.

The bundled lesson guides and the workbench's own wording are trusted and are not escaped.

Error messages do not show where files live on the server: :func:`hide_paths` shortens every absolute path to
``…/`` and its last part (``/home/me/data/x.csv`` -> ``…/x.csv``) in the text of an exception before it reaches
the page (:func:`error_text`); the server's terminal keeps the full paths.
"""

from __future__ import annotations

import re

#: Longest untrusted text shown by default, characters; longer text is cut and ends with an ellipsis.
MAX_LEN = 300
ELLIPSIS = "\u2026"

#: C0 and C1 control characters and DEL (newlines and tabs included: untrusted text stays on one line), and the
#: Unicode direction overrides that can make text read differently from what it is.
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069\u200e\u200f]")

#: HTML-active characters become entities; markdown-active punctuation is backslash-escaped (CommonMark allows
#: a backslash before any ASCII punctuation). One translation table, so nothing is escaped twice.
_ESCAPES = str.maketrans(
    {
        "&": "&amp;",
        "<": "&lt;",
        ">": "&gt;",
        "\\": "\\\\",
        "`": "\\`",
        "*": "\\*",
        "_": "\\_",
        "[": "\\[",
        "]": "\\]",
        "|": "\\|",
        "#": "\\#",
        "!": "\\!",
        "~": "\\~",
        "$": "\\$",
    }
)

#: An absolute path of two or more parts (POSIX ``/a/b``, ``~/a/b``, Windows ``C:\a\b``) that does not continue
#: a word, a URL (``http://x/y``) or a relative path (``a/b``); group 1 is its last part.
_ABS_PATH = re.compile(
    r"(?<![\w:/.~\\-])(?:~|[A-Za-z]:)?(?:[/\\][^\s/\\'\"`<>|,;:()\[\]]+){1,}[/\\]"
    r"([^\s/\\'\"`<>|,;:()\[\]]+)"
)

#: What makes a line a list item, a heading underline or a thematic break when it starts the text.
_LINE_START = re.compile(r"^(\s*\d*)([-+=.)])")


def clean_text(text, max_len: int = MAX_LEN) -> str:
    """``text`` as one line of plain text: control characters become spaces, the ends are trimmed, and the text is
    cut to ``max_len`` characters.

    For widgets that show plain text (notifications, hints): no markup escaping.

    Parameters
    ----------
    text : object
        Anything; ``str(text)`` is shown (``None`` gives ``""``).
    max_len : int
        Longest result, characters (the ellipsis included).
    """
    if text is None:
        return ""
    s = text if isinstance(text, str) else str(text)
    if len(s) > 4 * max_len + 64:  # cut before the regular expression: a 3 MB header is not scanned whole
        s = s[: 4 * max_len + 64]
    s = _CONTROL.sub(" ", s).strip()
    if len(s) > max_len:
        s = s[: max(max_len - 1, 0)].rstrip() + ELLIPSIS
    return s


def hide_paths(text: str) -> str:
    """``text`` with every absolute path cut to ``…/`` and its last part (where a file lives on the server is
    not the page's business; the file's name is)."""
    return _ABS_PATH.sub(lambda m: f"{ELLIPSIS}/{m.group(1)}", text)


def error_text(exc: BaseException) -> str:
    """An exception's message for the page: its text with absolute paths hidden (:func:`hide_paths`), cut to a
    length the page can hold before escaping (:func:`clean_text` cuts it further)."""
    s = str(exc)
    return hide_paths(s[:20_000])


def safe_text(text, max_len: int = MAX_LEN) -> str:
    """Untrusted ``text`` ready to be put inside markdown: shown as the characters it holds, never as markup.

    Control characters become spaces (the text stays on one line), the text is cut to ``max_len`` characters
    with an ellipsis, ``& < >`` become HTML entities and markdown's active punctuation (``\\ ` * _ [ ] | # ! ~ $``,
    and a list or heading marker at the start) is escaped with a backslash.

    Parameters
    ----------
    text : object
        Anything; ``str(text)`` is shown (``None`` gives ``""``).
    max_len : int
        Longest shown text, characters (before escaping, the ellipsis included).

    Returns
    -------
    str
        Markdown that renders as the (cut) text.

    Examples
    --------
    >>> safe_text("<img src=x onerror=alert(1)>")
    '&lt;img src=x onerror=alert(1)&gt;'
    >>> safe_text("pump_interference")
    'pump\\\\_interference'
    """
    s = clean_text(text, max_len).translate(_ESCAPES)
    return _LINE_START.sub(lambda m: m.group(1) + "\\" + m.group(2), s, count=1)


def safe_code(text, max_len: int = MAX_LEN) -> str:
    """Untrusted ``text`` as an inline code span: no markup is parsed inside it, so only backticks (which would
    end the span) are replaced, by ``'``; control characters and length as :func:`clean_text`."""
    s = clean_text(text, max_len).replace("`", "'")
    return f"`{s}`" if s.strip() else "` `"
