"""Fixtures the orchestrator's tests share: an in-process service (or several) on the test's loopback endpoint,
a Zenoh client session to it, and the test namespace's keys. A module that needs another kind defines its own."""

from __future__ import annotations

import errno
import os
import stat
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from orchestrator import transport
from orchestrator.protocol import Keys
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from storage.catalog import Catalog
from workers.collect import collect_episode, create_eval_split


@pytest.fixture
def make_service(data_dir: Path, endpoint: str, namespace: str):
    services: list[Service] = []

    def make(**kw: Any) -> Service:
        wall_clock, elapsed = kw.pop("wall_clock", time.time), kw.pop("elapsed", time.monotonic)
        cfg = ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,),
                            lease_s=kw.pop("lease_s", 30.0), reap_interval_s=kw.pop("reap_interval_s", 0.05),
                            lost_worker_grace_s=kw.pop("lost_worker_grace_s", 0.0), **kw)  # a lost worker: at once
        service = Service(cfg, wall_clock=wall_clock, elapsed=elapsed)
        service.start()
        services.append(service)
        return service

    yield make
    for service in services:
        service.stop()


@pytest.fixture
def service(make_service) -> Service:
    return make_service()


@pytest.fixture()
def procs():
    """Processes a test starts (anything with ``stop()``: test_secure's ``Proc``), stopped last first after it."""
    started: list = []
    yield started
    for p in reversed(started):
        p.stop()


@pytest.fixture
def client(endpoint: str):
    session = transport.open_session(connect=[endpoint])
    yield session
    session.close()


@pytest.fixture
def keys(namespace: str) -> Keys:
    return Keys(namespace)


class FailingSyncs:
    """``os.fsync`` of the files under ``directory`` fails with ``OSError(code)`` until ``heal()``: a disk that
    is full, then has room again (file systems that allocate late, and NFS, say so at the fsync). Only the
    files there: SQLite syncs its own files without Python's ``os.fsync``, so the catalog's rows stay
    writable, as when the episodes are on a disk of their own."""

    def __init__(self, directory: Path, monkeypatch, code: int = errno.ENOSPC) -> None:
        self.directory, self.code, self.failed = directory, code, 0
        self._real, self._healed = os.fsync, threading.Event()
        monkeypatch.setattr(os, "fsync", self._fsync)

    def _fsync(self, fd: int) -> None:
        if (not self._healed.is_set() and stat.S_ISREG(os.fstat(fd).st_mode)  # a file's, not a folder's
                and Path(os.readlink(f"/proc/self/fd/{fd}")).is_relative_to(self.directory)):
            self.failed += 1
            raise OSError(self.code, os.strerror(self.code))
        self._real(fd)

    def heal(self) -> None:
        """The disk has room again: every fsync from now on goes through."""
        self._healed.set()


def small_training_data(data: Path, steps: int = 12) -> Path:
    """A data directory with a 4-episode eval split and 6 training episodes (16 px, 12 steps): enough for a tiny
    retrain."""
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=4, seed=1, steps=steps, image_size=16)
    planner = UniformPlanner(UniformPlannerConfig(steps=steps), np.random.default_rng(0))
    for i, r in enumerate(planner.seed(6)):
        catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy,
                                            policy_params=r.policy_params, seed=i, steps=steps, image_size=16))
    return data
