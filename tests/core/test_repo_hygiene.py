"""The repository reads as reference: short docs, links that resolve, no history in place of reasons.

* every text file in ``docs/`` and ``benchmarks/results/`` is at most :data:`MAX_LINES` lines (one
  current table per benchmark, not a log of runs);
* every relative Markdown link in the README, ``docs/``, ``benchmarks/`` and ``tests/data/`` names a
  file of the repository, and every repository path a doc or a comment cites (``docs/….md``,
  ``benchmarks/….py``, ``tests/…``) exists;
* no doc, comment or docstring under ``docs/``, ``benchmarks/``, ``artdef_addon/``, ``operators/``,
  ``panels/``, ``tests/`` or ``scripts/`` points at the history of the work (issue numbers, work
  stops, branch and run labels) instead of stating the reason: that history lives in the commit
  messages. The method notes are cited by file (``docs/method_notes.md §N``), not as a bare name.

Only text is read (files with a NUL byte in their first 8 KB are skipped); the files are those git
tracks when the tree is a git checkout, else every file under those folders.
"""
import os
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MAX_LINES = 300
#: folders whose every text file is reference: docs and the benchmarks' current tables
SHORT = ("docs", "benchmarks/results")
#: folders (and files) read for history and for paths that must exist
SCANNED = ("docs", "benchmarks", "artdef_addon", "operators", "panels", "tests", "scripts", "README.md")
#: Markdown read for links
LINKED = ("README.md", "docs", "benchmarks", "tests/data")
TEXT_SUFFIXES = (".md", ".py", ".sh", ".toml", ".txt", ".js", ".ini", ".cfg")
SELF = Path(__file__).resolve()

#: what the history of the work looks like when it stands in a doc or a comment for a reason
HISTORY = [
    (re.compile(r"\b[Ii]ssues? \d+\b"), "an issue number"),
    (re.compile(r"\b[Ss]top \d+\b"), "a work stop"),
    (re.compile(r"\b(?:speed|auto|kernel|lock)\d{1,2}\b"), "a branch or run label"),
    (re.compile(r"\bQA\b"), "a QA pass"),
    (re.compile(r"\b(?:first|second|third|fourth|fifth) (?:speed )?push\b", re.I), "a push of work"),
    (re.compile(r"\b(?:this|that) (?:stop|session)\b"), "a work stop or session"),
    (re.compile(r"\bbranch `|\bon (?:this|the) branch\b"), "a branch"),
    (re.compile(r"\b(?:another|other) engineers?\b"), "a person"),
    (re.compile(r"\bMETHOD §"), "the method notes by a bare name (cite docs/method_notes*.md)"),
]
#: Markdown only: "#12"-style issue references
ISSUE_REF = re.compile(r"(?<![\w&/#])#\d{1,4}\b")
#: a repository path cited in a doc or a comment
CITED = re.compile(r"(?<![\w./-])((?:docs|benchmarks|tests|scripts|artdef_addon|operators|panels)/"
                   r"[\w./-]*\w\.(?:md|py|npz|sh|png|js|toml))\b")
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REF_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$", re.M)


def _files(tops):
    """The repository's files under ``tops`` (folders or files, relative to the root)."""
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--", *tops], capture_output=True,
                             check=True).stdout.decode("utf-8", "surrogateescape")
        paths = [ROOT / p for p in out.split("\0") if p]
    except (OSError, subprocess.CalledProcessError):
        paths = []
        for top in tops:
            p = ROOT / top
            if p.is_file():
                paths.append(p)
            for dirpath, dirnames, names in os.walk(p):
                dirnames[:] = [d for d in dirnames if not d.startswith(".") and d != "__pycache__"]
                paths += [Path(dirpath) / n for n in names]
    return sorted(p for p in paths if p.is_file())


def _text(path):
    """The file's text, or None for a binary file."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", "replace")


def _prose(markdown):
    """Markdown without its fenced code blocks and inline code spans (links there are examples)."""
    markdown = re.sub(r"^(```|~~~).*?^\1[^\n]*$", "", markdown, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", markdown)


def test_docs_and_result_tables_are_short():
    long = []
    for path in _files(SHORT):
        text = _text(path)
        if text is not None and text.count("\n") + (not text.endswith("\n") and bool(text)) > MAX_LINES:
            long.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
    assert not long, f"over {MAX_LINES} lines (keep the current figures, fold the rest into one line each): {long}"


def test_markdown_links_name_files_of_the_repository():
    broken = []
    for path in _files(LINKED):
        if path.suffix != ".md":
            continue
        text = _prose(_text(path) or "")
        for target in LINK.findall(text) + REF_LINK.findall(text):
            if re.match(r"[A-Za-z][\w+.-]*:", target) or target.startswith("#"):
                continue                                   # a URL, a mail address or an anchor
            local = target.split("#", 1)[0].split("?", 1)[0]
            if local and not (path.parent / local).exists():
                broken.append(f"{path.relative_to(ROOT)}: ({target})")
    assert not broken, f"links to files that do not exist: {broken}"


def test_cited_repository_paths_exist():
    missing = set()
    for path in _files(SCANNED):
        if path == SELF or path.suffix not in TEXT_SUFFIXES:
            continue
        for cited in CITED.findall(_text(path) or ""):
            if not ((ROOT / cited).exists() or (path.parent / cited).exists()):
                missing.add(f"{path.relative_to(ROOT)}: {cited}")
    assert not missing, f"cited files that do not exist: {sorted(missing)}"


def test_no_history_in_place_of_reasons():
    found = []
    for path in _files(SCANNED):
        if path == SELF or path.suffix not in TEXT_SUFFIXES:
            continue
        text = _text(path)
        if text is None:
            continue
        checks = HISTORY + ([(ISSUE_REF, "an issue reference")] if path.suffix == ".md" else [])
        for n, line in enumerate(text.splitlines(), 1):
            for pattern, what in checks:
                m = pattern.search(line)
                if m:
                    found.append(f"{path.relative_to(ROOT)}:{n}: {what}: {m.group(0)!r}")
    assert not found, ("say what is true and why, not when or by whom it changed (history goes in the "
                       f"commit message): {found}")


def test_the_checks_catch_what_they_are_for(tmp_path):
    """The patterns find the history they are meant for and pass the reference text around them."""
    def history(line):
        return [what for pattern, what in HISTORY if pattern.search(line)]
    assert history("the wolf's fit, stop 29") and history("as issue 16 asks") and history("on branch `speed2`")
    assert history("the third speed push") and history("a rig made for the QA pass") and history("METHOD §7.3")
    assert history("kernel16's cheaper kernels") and history("another engineer's run")
    assert not history("the search stops at 23 links") and not history("Blender's session folder, the session's own")
    assert history("measured this stop") and history("at that session")
    assert not history("a stop of the upward pass, grown links") and not history("docs/method_notes_model.md §7.3")
    assert not history("the generated branching object, 11 links") and not history("stopped at 24")
    assert ISSUE_REF.search("see #12") and not ISSUE_REF.search("a colour #1f77b4, [x](#section-2)")
    md = "[a](docs/x.md) `[b](nowhere.md)`\n```\n[c](nowhere.md)\n```\n[d]: ../e.md\n"
    assert LINK.findall(_prose(md)) == ["docs/x.md"] and REF_LINK.findall(_prose(md)) == ["../e.md"]
    assert CITED.findall("see ``docs/speed.md``, benchmarks/results/*.md and benchmarks/bench_core.py.") == \
        ["docs/speed.md", "benchmarks/bench_core.py"]
