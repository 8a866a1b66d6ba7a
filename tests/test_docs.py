"""The documentation stays true to the code: the generated command reference is current, every
command is documented, links resolve, and the pages describe what is (not how it came to be)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
COMMANDS_MD = ROOT / "docs" / "commands.md"
README_MAX_BYTES = 15_000

HISTORY_WORDS = [
    r"\bfirst version\b",
    r"\bprevious default\b",
    r"\bissue \d+\b",
    r"\bissue #\d+",
    r"\b(first|second|third|next|later) round\b",
    r"\bno longer\b",
    r"\bused to\b",
    r"\bnew default\b",
    r"\bold default\b",
    r"\bformerly\b",
    r"\bpreviously\b",
    r"\bwe changed\b",
    r"\bhas been (replaced|removed|changed)\b",
]


def _doc_pages() -> list[Path]:
    return [README, *sorted((ROOT / "docs").glob("*.md"))]


def _commands_doc():
    spec = importlib.util.spec_from_file_location("commands_doc", ROOT / "scripts" / "commands_doc.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _command_names() -> list[str]:
    import typer

    from contact_viz.cli import app

    group = typer.main.get_command(app)
    return list(group.list_commands(type(group).context_class(group, info_name="contact-viz")))


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


# ---------------------------------------------------------------- markdown reading

_FENCE = re.compile(r"^\s{0,3}(`{3,}|~{3,})")


def _prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks, inline code spans blanked."""
    out, fence = [], None
    for number, line in enumerate(text.splitlines(), 1):
        match = _FENCE.match(line)
        if fence is None and match:
            fence = match.group(1)[0] * len(match.group(1))
            continue
        if fence is not None:
            if line.strip().startswith(fence) and set(line.strip()) <= {fence[0]}:
                fence = None
            continue
        out.append((number, re.sub(r"(`+)(?:(?!\1).)+?\1", lambda m: " " * len(m.group(0)), line)))
    return out


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: its text, lowercase, punctuation other than '-' and '_' dropped,
    spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text only
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    """Every anchor of a markdown page: headings (duplicates get -1, -2 ...) and <a name/id="...">."""
    text = path.read_text(encoding="utf-8")
    anchors, seen = set(), {}
    in_fence = {n for n, _ in enumerate(text.splitlines(), 1)} - {n for n, _ in _prose_lines(text)}
    for number, line in enumerate(text.splitlines(), 1):
        if number in in_fence:
            continue
        match = re.match(r"^\s{0,3}#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            slug = _slug(match.group(1))
            count = seen.get(slug, 0)
            seen[slug] = count + 1
            anchors.add(slug if count == 0 else f"{slug}-{count}")
    anchors |= set(re.findall(r"<a\s+(?:name|id)=\"([^\"]+)\"", text))
    return anchors


_INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")


def _links(path: Path) -> list[tuple[int, str]]:
    text = path.read_text(encoding="utf-8")
    found = []
    for number, line in _prose_lines(text):
        found += [(number, m.group(1)) for m in _INLINE_LINK.finditer(line)]
        match = _REFERENCE_LINK.match(line)
        if match:
            found.append((number, match.group(1)))
    return found


# ---------------------------------------------------------------- the tests

def test_commands_doc_is_current():
    expected = _commands_doc().render()
    current = COMMANDS_MD.read_text(encoding="utf-8") if COMMANDS_MD.exists() else ""
    assert current == expected, (f"{_rel(COMMANDS_MD)} is stale (the CLI's commands, options or help changed): "
                                 "run `python scripts/commands_doc.py`")


def test_no_history_words():
    patterns = [re.compile(p, re.IGNORECASE) for p in HISTORY_WORDS]
    hits = []
    for page in _doc_pages():
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            for pattern in patterns:
                match = pattern.search(line)
                if match:
                    hits.append(f"{_rel(page)}:{number}: {match.group(0)!r}: {line.strip()[:120]}")
    assert not hits, ("the docs describe the project's history; say what is instead:\n" + "\n".join(hits))


def test_docs_links_resolve():
    broken = []
    for page in _doc_pages():
        for number, target in _links(page):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("//"):
                continue  # http:, https:, mailto: ...
            file_part, _, anchor = unquote(target).partition("#")
            linked = page if file_part == "" else (page.parent / file_part.split("?")[0]).resolve()
            where = f"{_rel(page)}:{number}: ({target})"
            if not linked.exists():
                broken.append(f"{where}: no such file")
            elif anchor and linked.suffix.lower() == ".md" and anchor.lower() not in _anchors(linked):
                broken.append(f"{where}: no heading #{anchor} in {_rel(linked)}")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_readme_size():
    size = README.stat().st_size
    assert size <= README_MAX_BYTES, (f"README.md is {size:,} bytes, more than {README_MAX_BYTES:,}: move detail "
                                      "into docs/ and link to it")


def test_every_command_has_a_readme_row_and_docs_section():
    readme = README.read_text(encoding="utf-8").splitlines()
    reference = COMMANDS_MD.read_text(encoding="utf-8").splitlines() if COMMANDS_MD.exists() else []
    missing = []
    for name in _command_names():
        row = re.compile(rf"`contact-viz {re.escape(name)}(?![\w-])")
        if not any(line.startswith(f"| `contact-viz {name}") or row.search(line) for line in readme):
            missing.append(f"README.md: no command-table row for `contact-viz {name}`")
        if f"## contact-viz {name}" not in [line.rstrip() for line in reference]:
            missing.append(f"{_rel(COMMANDS_MD)}: no heading '## contact-viz {name}'")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize("heading, slug", [
    ("contact-viz view", "contact-viz-view"),
    ("`contact-viz SESSION` — the visual debugger (also `contact-viz view SESSION`)",
     "contact-viz-session--the-visual-debugger-also-contact-viz-view-session"),
    ("Set-up: two commands", "set-up-two-commands"),
    ("tau_tool and [N1](x.md)", "tau_tool-and-n1"),
])
def test_slug_follows_github(heading, slug):
    assert _slug(heading) == slug


def _options_of(name: str) -> set[str]:
    import typer

    from contact_viz.cli import app

    group = typer.main.get_command(app)
    command = group.get_command(type(group).context_class(group, info_name="contact-viz"), name)
    params = [*command.params, *group.params]  # the group's (--verbose) are accepted after the command too
    return {opt for param in params for opt in (*param.opts, *param.secondary_opts)} | {"--help"}


_COMMAND_LINE = re.compile(r"\bcontact-viz((?:[ \t]+[^\s`|#]+)+)")


def test_every_option_quoted_in_the_docs_exists():
    """Each `contact-viz ...` line in README and docs/ (code blocks, tables, text) uses only options its
    command has: a renamed or removed option cannot stay in the docs."""
    commands = set(_command_names())
    wrong = []
    for page in _doc_pages():
        if page == COMMANDS_MD:
            continue
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            for match in _COMMAND_LINE.finditer(line):
                words = match.group(1).split()
                name = words[0] if words[0] in commands else "view"  # `contact-viz SESSION` is `view`
                known = _options_of(name)
                for word in words:
                    option = word.split("=", 1)[0].rstrip(".,;:)")
                    if option.startswith("--") and len(option) > 2 and option not in known:
                        wrong.append(f"{_rel(page)}:{number}: `contact-viz {name}` has no option {option}")
    assert not wrong, "\n".join(wrong)
