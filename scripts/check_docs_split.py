"""Check that nothing the README carried was lost when it was split into README.md + docs/.

    python scripts/check_docs_split.py OLD_README.md      # e.g. from `git show REV:README.md`

Every table row, figure (image link) and line of a code block of the old README must still be in
README.md, docs/*.md or benchmarks/results/*.md (whitespace-normalised). Prints what is missing
and exits 1 if anything is.
"""
import glob
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _norm(s):
    return re.sub(r"\s+", " ", s).strip()


def items(text):
    """Table rows, image links and code-block lines of a Markdown text."""
    out, fence = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        s = line.strip()
        if fence and s:
            out.append(("code", s))
        elif s.startswith("|") and not re.fullmatch(r"\|[\s|:-]*\|", s):
            out.append(("table row", s))
        elif "![" in s:
            out.append(("figure", re.search(r"!\[[^\]]*\]\(([^)]+)\)", s).group(1)))
    return out


def main(argv):
    old = open(argv[1], encoding="utf-8").read()
    files = [os.path.join(ROOT, "README.md")] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md"))) \
        + sorted(glob.glob(os.path.join(ROOT, "benchmarks", "results", "*.md")))
    corpus = _norm("\n".join(open(f, encoding="utf-8").read() for f in files))
    missing = []
    for kind, s in items(old):
        if kind == "figure":
            name = os.path.basename(s)
            if not any(os.path.basename(p) == name for p in glob.glob(os.path.join(ROOT, "docs", "**", "*"),
                                                                       recursive=True)
                       + glob.glob(os.path.join(ROOT, "benchmarks", "results", "**", "*"), recursive=True)):
                missing.append((kind, s))
        elif _norm(s) not in corpus:
            missing.append((kind, s))
    n = len(items(old))
    for kind, s in missing:
        print(f"missing {kind}: {s[:160]}")
    print(f"{n - len(missing)} of {n} table rows, figures and code lines of {argv[1]} found in "
          f"README.md, docs/ and benchmarks/results/")
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
