"""A CSV's line ends as other programs write them, and damaged by a carriage return (CR) inside a line: the files
every CSV reader of magcal (whole file with pyarrow or line by line, blocks, ``--drop-bad``, the row count, the
survey's partitions, ``magcal apply``) must read to the same samples or refuse with the same message."""

from __future__ import annotations

#: Variants every reader reads as the LF file: CRLF; CRs piled before the LF (a CRLF file written again in text
#: mode on Windows); a last line ending in a CR.
READ = ["lf", "crlf", "cr_cr_lf", "cr_at_the_end"]
#: Variants every reader refuses: old Mac line ends (CR only); a row whose LF became a CR, in an LF and in a CRLF
#: file (pyarrow read it as two rows); a CR at the start of a row (pyarrow skipped it) or inside a value; one in a
#: metadata line.
REFUSED = [
    "cr_only",
    "rows_joined_by_cr",
    "rows_joined_by_cr_in_crlf",
    "cr_before_a_row",
    "cr_in_a_value",
    "cr_in_head",
]
VARIANTS = READ + REFUSED

OLD_MAC = r"the lines end with a lone carriage return \(old Mac style\).*convert the file to Unix \(LF\) or Windows"


def stray(line_no) -> str:
    """The refusal of a CR inside line ``line_no`` (a regular expression)."""
    return rf": line {line_no} holds a carriage return \(CR, \\r\) inside the line; .*convert the file's line endings"


def line_end_variant(text: str, variant: str, where=0.75):
    """``text`` (a CSV written by magcal: LF line ends, ``#`` lines, the header, the rows) as ``variant`` (UTF-8
    bytes), and the message its readers give (a regular expression), None when they read it. A damaged row is the
    one ``where`` of the way through the rows."""
    lines = text.rstrip("\n").split("\n")
    header = next(k for k, line in enumerate(lines) if not line.startswith("#"))
    k = header + 1 + int(where * (len(lines) - header - 1))  # the damaged row's index: file line k + 1
    refusal = None
    if variant == "crlf":
        out = "\r\n".join(lines) + "\r\n"
    elif variant == "cr_cr_lf":
        out = "\r\r\n".join(lines) + "\r\r\n"
    elif variant == "cr_at_the_end":
        out = "\n".join(lines) + "\r"
    elif variant == "cr_only":
        out, refusal = "\r".join(lines) + "\r", OLD_MAC
    elif variant in ("rows_joined_by_cr", "rows_joined_by_cr_in_crlf"):
        end = "\r\n" if variant.endswith("crlf") else "\n"
        out = end.join(lines[:k] + [lines[k] + "\r" + lines[k + 1]] + lines[k + 2 :]) + end
        refusal = stray(k + 1)
    elif variant == "cr_before_a_row":
        out, refusal = "\n".join(lines[:k] + ["\r" + lines[k]] + lines[k + 1 :]) + "\n", stray(k + 1)
    elif variant == "cr_in_a_value":
        cut = lines[k].index(",") + 3
        bad = lines[k][:cut] + "\r" + lines[k][cut:]
        out, refusal = "\n".join(lines[:k] + [bad] + lines[k + 1 :]) + "\n", stray(k + 1)
    elif variant == "cr_in_head":
        assert lines[0].startswith("#")
        out, refusal = "\n".join([lines[0] + "\rmore"] + lines[1:]) + "\n", stray(1)
    else:
        assert variant == "lf", variant
        out = text
    return out.encode("utf-8"), refusal
