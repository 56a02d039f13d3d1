"""What ``activecollect run`` reads of the catalog besides its counts: episodes it loads past a lost or damaged file,
and the eval episodes left outside the pinned split (said by ``run`` and ``eval-split create`` alike).

Free of torch: the CLI's ``eval-split create`` imports it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from storage.catalog import Catalog
from storage.errors import DAMAGED_EPISODE_ERRORS, StorageError
from storage.quarantine import clean_reason, looks_unmounted
from storage.records import Episode

log = logging.getLogger(__name__)


def load_episodes(catalog: Catalog, ids: Iterable[str], purpose: str, quarantine: bool = True) -> list[Episode]:
    """The episodes of ``ids`` that load, in order; each one that does not is left out with a warning naming
    ``purpose`` (what they are loaded for), so one lost file neither stops the run nor keeps it from resuming.

    ``quarantine``: a train episode whose file is gone or no longer holds the bytes indexed is quarantined, as
    a retrain does (``uncertainty.data.load_train``); unless a repair came first (``only_if_damaged``), and then
    it is loaded again; and unless most of them are (``storage.quarantine.looks_unmounted``: a disk not mounted),
    as a retrain does too. Eval-split episodes cannot be quarantined (the split is fixed): give False.
    """
    ids = list(ids)
    episodes: dict[str, Episode] = {}
    damaged: dict[str, StorageError] = {}
    for episode_id in ids:
        try:
            episodes[episode_id] = catalog.load(episode_id)
        except DAMAGED_EPISODE_ERRORS as exc:
            # one quarantined since its id was read (`episodes quarantine` moved its file aside) is left out, and is
            # neither a damaged file nor a sign of an unmounted disk (as in `uncertainty.data.load_train`)
            if not catalog.get(episode_id).quarantined:
                damaged[episode_id] = exc
        except StorageError as exc:  # a read that may pass (permissions, I/O): nothing to quarantine for
            log.warning("episode %s left out of %s: %s", episode_id, purpose, exc)
    if quarantine and looks_unmounted(len(damaged), len(episodes) + len(damaged)):
        first, exc = next(iter(damaged.items()))
        log.warning("the files of %d of %d episodes loaded for %s are missing or damaged (first %s: %s); left out, "
                    "nothing quarantined: check that the data directory's disk is there and readable, then "
                    "`activecollect episodes verify --quarantine`", len(damaged), len(episodes) + len(damaged),
                    purpose, first, exc)
    else:
        for episode_id, exc in damaged.items():
            if quarantine and (episode := _quarantine(catalog, episode_id, exc, purpose)) is not None:
                episodes[episode_id] = episode
            elif not quarantine:
                log.warning("episode %s left out of %s: %s", episode_id, purpose, exc)
    return [episodes[i] for i in ids if i in episodes]


def _quarantine(catalog: Catalog, episode_id: str, damaged: StorageError, purpose: str) -> Episode | None:
    """Quarantine the train episode ``episode_id`` found ``damaged``; the episode when a repair came first."""
    reason = clean_reason(f"found by activecollect run: {damaged}")
    try:
        row = catalog.quarantine(episode_id, reason, only_if_damaged=True)
        if not row.quarantined:  # its bytes were ingested again since the read
            return catalog.load(episode_id)
        if row.quarantined != reason:  # someone else's quarantine, committed since the read: not ours to report
            return None
    except StorageError as exc:
        log.warning("episode %s left out of %s: %s; and it cannot be quarantined now: %s", episode_id, purpose,
                    damaged, exc)
        return None
    log.warning("episode %s quarantined and left out of %s: %s", episode_id, purpose, damaged)
    return None


def eval_leftovers_warning(catalog: Catalog) -> str:
    """The warning for eval episodes of ``catalog`` that are not in its pinned split (an interrupted ``eval-split
    create`` or ``run`` taken up with other flags, or episodes ingested as eval since); "" when there are none."""
    split = catalog.eval_split()
    left = catalog.count(split="eval") - (len(split.ids) if split else 0)
    if left <= 0:
        return ""
    return (f"{left} eval episode(s) in {catalog.data_dir} are not in the split (an interrupted `eval-split create` "
            "or `run` with other flags, or ingested as eval since): nothing trains or evaluates on them")
