"""A file, or a link to no directory, where the catalog's episodes/ or the registry's models/ goes: each component
raises its own error, which is also a ``MisplacedFolderError`` (what the service's sweep passes over), with the
same message as before (real folders, files and links on disk)."""

from __future__ import annotations

from functools import partial

import pytest

from storage.catalog import Catalog
from storage.errors import (CatalogError, CatalogFolderError, MisplacedFolderError, RegistryError,
                            RegistryFolderError)
from storage.models import ModelRegistry


@pytest.mark.parametrize("link", [False, True])
@pytest.mark.parametrize(("folder", "opener", "component", "error", "purpose"), [
    ("episodes", Catalog, CatalogError, CatalogFolderError, "the catalog keeps its episode files there"),
    ("models", ModelRegistry, RegistryError, RegistryFolderError, "the registry keeps its checkpoints there"),
    # a reader that makes no folder (the dashboard, `models ls`) still names what is in its place
    ("episodes", partial(Catalog, make_episodes_dir=False), CatalogError, CatalogFolderError,
     "the catalog keeps its episode files there"),
    ("models", partial(ModelRegistry, make_models_dir=False), RegistryError, RegistryFolderError,
     "the registry keeps its checkpoints there"),
], ids=["episodes", "models", "episodes read-only", "models read-only"])
def test_a_file_where_a_folder_goes_is_the_components_misplaced_folder_error(tmp_path, link, folder, opener,
                                                                           component, error, purpose) -> None:
    data = tmp_path / "data"
    Catalog(data)  # (the registry refuses a data directory whose catalog is lost)
    where = data / folder
    if where.exists():
        where.rmdir()
    if link:  # a volume not mounted
        where.symlink_to(tmp_path / "volume")
        said = (f"{where} is a link to {tmp_path / 'volume'}, which is not a directory (a volume not mounted?): "
                f"{purpose}; mount it, or point the link at the folder")
    else:
        where.write_text("not a folder")
        said = f"{where} is not a directory: {purpose}; move the file away"
    with pytest.raises(error) as raised:
        opener(data)
    assert isinstance(raised.value, component) and isinstance(raised.value, MisplacedFolderError)
    assert str(raised.value) == said
    assert where.is_symlink() if link else where.read_text() == "not a folder"  # left where it was


def test_a_registry_refused_for_another_reason_is_no_misplaced_folder_error(tmp_path) -> None:
    (tmp_path / "models" / "m000001-0badf00d").mkdir(parents=True)  # a data directory whose catalog is lost
    with pytest.raises(RegistryError, match="catalog.sqlite is missing") as raised:
        ModelRegistry(tmp_path)
    assert not isinstance(raised.value, MisplacedFolderError)
