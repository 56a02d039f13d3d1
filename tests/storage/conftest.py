"""Fixtures the storage tests share: a seeded generator, and a catalog and a model registry in a fresh data
directory."""

from __future__ import annotations

import numpy as np
import pytest

from storage.catalog import Catalog
from storage.models import ModelRegistry


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


@pytest.fixture
def cat(tmp_path) -> Catalog:
    return Catalog(tmp_path / "data")


@pytest.fixture
def reg(tmp_path) -> ModelRegistry:
    return ModelRegistry(tmp_path / "data")
