"""Fixtures the orchestrator's tests share: an in-process service (or several) on the test's loopback endpoint,
a Zenoh client session to it, and the test namespace's keys. A module that needs another kind defines its own."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from orchestrator import transport
from orchestrator.protocol import Keys
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig


@pytest.fixture
def make_service(data_dir: Path, endpoint: str, namespace: str):
    services: list[Service] = []

    def make(**kw: Any) -> Service:
        cfg = ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,),
                            lease_s=kw.pop("lease_s", 30.0), reap_interval_s=kw.pop("reap_interval_s", 0.05), **kw)
        service = Service(cfg)
        service.start()
        services.append(service)
        return service

    yield make
    for service in services:
        service.stop()


@pytest.fixture
def service(make_service) -> Service:
    return make_service()


@pytest.fixture
def client(endpoint: str):
    session = transport.open_session(connect=[endpoint])
    yield session
    session.close()


@pytest.fixture
def keys(namespace: str) -> Keys:
    return Keys(namespace)
