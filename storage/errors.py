"""The storage package's exceptions: one root, one subclass per way a thing on disk can be wrong."""


class StorageError(Exception):
    """Root of every error raised by ``storage``."""


class EpisodeError(StorageError):
    """An episode file could not be read or written."""


class TruncatedEpisodeError(EpisodeError):
    """The file ends before its MCAP footer / summary: a partial write or a cut transfer."""


class CorruptEpisodeError(EpisodeError):
    """The bytes are damaged: a CRC mismatch, an undecodable record, inconsistent lengths."""


class ForeignFileError(EpisodeError):
    """The file is not an activecollect episode (not MCAP, or MCAP without our channels/metadata)."""


class MissingEpisodeError(EpisodeError):
    """An indexed episode's file is gone from disk (deleted, or moved aside by ``Catalog.quarantine``)."""


class OversizedEpisodeError(EpisodeError):
    """The file's chunks would inflate to more than its frames need, or than the reader allows: refused
    before that memory is taken."""


class FrameSizeError(EpisodeError):
    """The file's frames are not the size the reader asked for (``read_episode``'s ``frame_size``): refused from
    its metadata, before a chunk is inflated."""

    def __init__(self, message: str, found: int, expected: int) -> None:
        super().__init__(message)
        self.found, self.expected = found, expected


#: What reading an indexed episode raises when its file no longer holds what was acknowledged (gone, other
#: bytes, an unreadable structure), unlike a read that may pass (permissions, I/O): what
#: ``Catalog.quarantine`` is for.
DAMAGED_EPISODE_ERRORS = (MissingEpisodeError, CorruptEpisodeError, TruncatedEpisodeError, ForeignFileError)


class MisplacedFolderError(StorageError):
    """A file, or a link to no directory, is where a folder of the data directory goes (``storage.files.make_folder``):
    nothing was made, and nothing is until it is moved away (or its volume mounted). Each component raises its own
    subclass (``CatalogFolderError`` ...), so it is also that component's error."""


class CatalogError(StorageError):
    """The catalog refused an operation (unknown id, conflicting row, bad split)."""


class CatalogFolderError(CatalogError, MisplacedFolderError):
    """A file, or a link to no directory, is where the catalog's episodes/ goes (see ``MisplacedFolderError``)."""


class OtherSplitError(CatalogError):
    """The bytes are an episode the catalog already indexes in another split (``split``: that one)."""

    def __init__(self, message: str, split: str) -> None:
        super().__init__(message)
        self.split = split


class NotFoundError(StorageError):
    """Nothing is stored under the id asked for (an unknown or ambiguous episode id, an unknown model
    version): the asker's mistake, which the CLI reports as a usage error (exit 2), unlike a damaged
    or unavailable store (exit 1). Each component raises its own subclass."""


class UnknownEpisodeError(CatalogError, NotFoundError):
    """No episode has this id (or, for a prefix, exactly one)."""


class StorageUnavailableError(StorageError):
    """The disk or the database could not be used for a reason that passes (no space left, an I/O error,
    a lock held past the busy timeout, a file system or database file that is read-only for now): nothing
    was changed, and the same call can succeed later. Each component raises its own subclass
    (``CatalogUnavailableError`` ...), so it is also that component's error."""


class CatalogUnavailableError(CatalogError, StorageUnavailableError):
    """The catalog's disk or database is unavailable for now (see ``StorageUnavailableError``)."""


class QueueError(StorageError):
    """A request-queue operation was refused (unknown id, illegal transition)."""


class QueueUnavailableError(QueueError, StorageUnavailableError):
    """The queue's database is unavailable for now (see ``StorageUnavailableError``)."""


class QueueClosedError(QueueError):
    """The queue was closed (its service is stopping): not the request's fault; asked again, the next service
    answers."""


class StaleLeaseError(QueueError):
    """A renew / upload / fail carried a fencing token that is no longer the live one."""


class RegistryError(StorageError):
    """The model registry refused an operation (unknown version, no champion to roll back to)."""


class UnknownModelError(RegistryError, NotFoundError):
    """No model has this version."""


class RegistryFolderError(RegistryError, MisplacedFolderError):
    """A file, or a link to no directory, is where the registry's models/ goes (see ``MisplacedFolderError``)."""


class RegistryUnavailableError(RegistryError, StorageUnavailableError):
    """The registry's disk or database is unavailable for now (see ``StorageUnavailableError``)."""


class CorruptCheckpointError(RegistryError):
    """A checkpoint's weights cannot be used: they do not match their recorded sha256, its files are
    unreadable, or (``PrunedCheckpointError``) they were deleted on purpose."""


class PrunedCheckpointError(CorruptCheckpointError):
    """The checkpoint's weights were deleted by ``ModelRegistry.prune``; its row and metrics remain."""


class BackupError(StorageError):
    """A backup could not be made (no catalog to copy, a destination in the way, a failed write)."""
