"""benchmarks/README.md is one page of headline figures: every script in benchmarks/ has a short block there with
its command line, the machine and the date of the run, and a link to its lab notes (benchmarks/notes/); every link in
the README and in the notes resolves, to a file and, where it names one, to a heading of that file."""

import re
from collections import Counter
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
README = BENCHMARKS / "README.md"
NOTES = BENCHMARKS / "notes"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py"))

#: Lines a script's block may take (its heading, the run line, a short table or a few lines): a longer one is lab
#: notes, which belong in benchmarks/notes/<script>.md.
MAX_BLOCK_LINES = 30

FENCE = re.compile(r"^\s*```")
HEADING = re.compile(r"^(#{1,6}) (.*)$")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _prose(path):
    """The lines of a markdown file outside fenced code blocks, with their line numbers."""
    inside = False
    for number, line in enumerate(path.read_text(encoding="utf-8").split("\n"), 1):
        if FENCE.match(line):
            inside = not inside
            continue
        if not inside:
            yield number, line


def _slug(heading):
    """GitHub's anchor for a heading: lower case, punctuation dropped (letters, digits, _, - and spaces kept),
    spaces turned into hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path):
    """The anchors of a markdown file's headings (a repeated one gets -1, -2, ... as on GitHub)."""
    seen = Counter()
    anchors = set()
    for _, line in _prose(path):
        match = HEADING.match(line)
        if match:
            slug = _slug(match.group(2))
            anchors.add(slug if not seen[slug] else f"{slug}-{seen[slug]}")
            seen[slug] += 1
    return anchors


def _links(path):
    """(line number, target) of every markdown link of a file, code spans and fenced blocks left out."""
    for number, line in _prose(path):
        for target in LINK.findall(re.sub(r"`[^`]*`", "code", line)):
            yield number, target


def _blocks():
    """{heading: its lines up to the next heading} for the README's headings of the third level."""
    blocks, current = {}, None
    for _, line in _prose(README):
        match = HEADING.match(line)
        if match:
            current = match.group(2) if len(match.group(1)) == 3 else None
            if current is not None:
                blocks[current] = [line]
        elif current is not None:
            blocks[current].append(line)
    return {heading: "\n".join(lines).rstrip() for heading, lines in blocks.items()}


def _markdown_files():
    return [README, *sorted(NOTES.glob("*.md"))]


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_script_has_a_headline_block_with_its_command_machine_date_and_notes(script):
    named = {heading: block for heading, block in _blocks().items() if f"`{script}`" in heading}
    assert named, (
        f"benchmarks/README.md: no heading names `{script}`; add '### What it measures (`{script}`)' with its headline "
        "figures (ours, the seed's method or the peers, the floor), its command, machine and date, and its lab notes "
        f"in benchmarks/notes/{Path(script).stem}.md"
    )
    command = re.compile(r"`(?:\w+=\S* )*python benchmarks/" + re.escape(script) + r"(?: [^`]*)?`")
    for heading, block in named.items():
        where = f"benchmarks/README.md, '### {heading}'"
        assert command.search(block), f"{where}: no command line `python benchmarks/{script} ...`"
        assert re.search(r"\b20\d\d-\d\d-\d\d\b", block), f"{where}: no date of the run (YYYY-MM-DD)"
        assert re.search(r"\b\d+-core\b", block), f"{where}: no machine (e.g. '2-core', '16-core')"
        assert re.search(r"\]\(notes/[^)]+\.md(?:#[^)]*)?\)", block), f"{where}: no link to its notes in notes/"


def test_each_headline_block_is_short():
    """Full tables, history and ad-hoc measurements go in benchmarks/notes/, not in the README."""
    long = {h: b.count("\n") + 1 for h, b in _blocks().items() if b.count("\n") + 1 > MAX_BLOCK_LINES}
    assert not long, (
        f"benchmarks/README.md: blocks longer than {MAX_BLOCK_LINES} lines: {long}; keep the headline there and move "
        "the rest to the script's file in benchmarks/notes/"
    )


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: p.relative_to(BENCHMARKS).as_posix())
def test_every_link_resolves(path):
    broken = []
    for number, target in _links(path):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto: are not checked here
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"line {number}: {target}: no such file")
        elif anchor and (linked.suffix != ".md" or anchor not in _anchors(linked)):
            broken.append(f"line {number}: {target}: no heading with the anchor #{anchor} in {linked.name}")
    assert not broken, f"benchmarks/{path.relative_to(BENCHMARKS).as_posix()}: " + "; ".join(broken)


def test_every_notes_file_is_reached_from_the_readme():
    assert NOTES.is_dir(), "benchmarks/notes/ is missing: the lab notes of each script live there"
    reached = set()
    for source in (README, NOTES / "README.md"):
        for _, target in _links(source):
            linked = (source.parent / target.partition("#")[0]).resolve()
            if linked.parent == NOTES.resolve():
                reached.add(linked.name)
    orphans = sorted({p.name for p in NOTES.glob("*.md")} - reached - {"README.md"})
    assert "README.md" in reached, "benchmarks/README.md does not link the notes' index, notes/README.md"
    assert not orphans, f"benchmarks/notes/: {orphans} linked from neither benchmarks/README.md nor notes/README.md"
