"""The read-only dashboard (``activecollect dashboard``) writes no folder into the data directory it shows: a
directory where no model was trained yet has no ``models/``, one where no episode was ingested (or whose folder is
gone) no ``episodes/``, and starting, then serving every page and endpoint, leaves it so."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from storage.catalog import Catalog
from storage.models import ModelRegistry
from tests.conftest import wait_for
from tests.orchestrator.test_dashboard import get
from tests.orchestrator.test_dashboard_hostile2 import ENDPOINTS


def _entries(data_dir) -> set[str]:
    """The data directory's entries, all the way down, but the database's own -wal/-shm (SQLite's to make, on any
    read)."""
    return {str(p.relative_to(data_dir)) for p in data_dir.rglob("*") if not p.name.startswith("catalog.sqlite-")}


@pytest.mark.parametrize("models", ["never trained", "folder removed"])
def test_the_dashboard_command_makes_no_folder(spawn, data_dir, models):
    Catalog(data_dir).episodes_dir.rmdir()  # the catalog alone: no episode ingested here, or its folder gone
    champion = None
    if models == "folder removed":  # rows left, their folder gone (a volume not mounted, an operator's rm)
        registry = ModelRegistry(data_dir)
        champion = registry.register(b"weights", {"members": 2}, {"h1_mse": 0.01}, "snap", "split-a")
        registry.gate(champion)
        shutil.rmtree(registry.models_dir)
    before = _entries(data_dir)
    assert before == {"catalog.sqlite"}
    proc = spawn("dashboard", "dashboard", "--data", str(data_dir), "--port", "0")
    found = wait_for(lambda: re.search(r"dashboard on (http://\S+)", proc.log()), timeout=60,
                     message="the dashboard to print its address")
    assert _entries(data_dir) == before, proc.log()
    for path in ENDPOINTS:
        status, _, _ = get(found.group(1) + path.lstrip("/"))
        assert status == 200, (path, proc.log())
        assert _entries(data_dir) == before, (path, proc.log())
    status, _, body = get(found.group(1) + "api/models")
    shown = json.loads(body)  # "no models", or the rows as they are
    assert status == 200 and shown["champion"] == champion
    assert [m["version"] for m in shown["models"]] == ([] if champion is None else [champion])
    stats = json.loads(get(found.group(1) + "api/stats")[2])
    assert (stats["champion_problem"] is None) == (champion is None), stats
