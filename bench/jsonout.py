"""What the bench scripts run as files share: their summary printed as JSON and, with --json, written too."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def emit(summary: Any, path: Path | None, indent: int = 1) -> int:
    """Print ``summary`` as JSON, write it to ``path`` as well when there is one; the script's exit status (0)."""
    text = json.dumps(summary, indent=indent)
    print(text)
    if path:
        path.write_text(text + "\n")
    return 0
