"""Lines of Python at most ``MAX_LINE`` characters, in every package, the benchmarks and the tests.

Long lines hid a bug once: a comment at a tuple's opening parenthesis swallowed the two entries after it
on the same line, and the test they belonged to never sent them.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("storage", "uncertainty", "workers", "orchestrator", "bench", "tests")
MAX_LINE = 120


def test_no_line_of_python_is_longer_than_the_limit() -> None:
    # (not below a hidden folder: `make bench` installs gym-pusht's own code into bench/.venv-pusht)
    files = sorted(p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py")
                   if not any(part.startswith(".") for part in p.relative_to(ROOT).parts))
    assert len(files) > 100  # (the folders were found)
    long = [f"{path.relative_to(ROOT)}:{n}: {len(line)} characters"
            for path in files
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if len(line) > MAX_LINE]
    assert not long, "\n".join(long)
