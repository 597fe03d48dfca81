"""Where a benchmark's Markdown table goes: its one file under ``benchmarks/results/``, replaced whole by the
latest run and headed by what that run was measured at (the checkout's commit, the UTC time, the machine's
load), so the file is always one current table rather than a log of runs."""
from __future__ import annotations

import datetime
import os
import platform
import subprocess

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def result_path(name: str) -> str:
    """``benchmarks/results/NAME``: a script's default ``--out``."""
    return os.path.join(HERE, "results", name)


def commit(repo: str = ROOT) -> str:
    """The short commit of the checkout at ``repo`` (``+`` when its tracked files differ from it), or ``unknown``."""
    try:
        sha = subprocess.run(["git", "-C", repo, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", repo, "diff", "--quiet", "HEAD"], capture_output=True).returncode
        return sha + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def stamp(repo: str = ROOT) -> str:
    """One line: commit, UTC date and time, load average over the last minute against the cores, the machine."""
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    try:
        load = f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    except OSError:
        load = f"{os.cpu_count()} cores"
    return (f"Measured at `{commit(repo)}`, {now}, {load}; {platform.machine()}, Python "
            f"{platform.python_version()}.")


def write(path: str, title: str, body: str, repo: str = ROOT) -> None:
    """Replace ``path`` with ``# title``, the stamp and ``body`` (written to a temporary file, then renamed)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(f"# {title}\n\n{stamp(repo)}\n\n{body.rstrip()}\n")
    os.replace(tmp, path)
    print("wrote", path)
