"""Fixtures the storage tests share: a seeded generator, and a catalog, a model registry and a request queue in a
fresh data directory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.queue import RequestQueue


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


@pytest.fixture
def cat(tmp_path) -> Catalog:
    return Catalog(tmp_path / "data")


@pytest.fixture
def reg(tmp_path) -> ModelRegistry:
    return ModelRegistry(tmp_path / "data")


@pytest.fixture
def queue(tmp_path: Path):
    q = RequestQueue(tmp_path / "catalog.sqlite")
    yield q
    q.close()
