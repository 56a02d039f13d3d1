"""Every process refuses to start a secure profile whose files are missing, in one line, exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest

from orchestrator.secure import SecureInitConfig, init_secure

COMMANDS = {
    "serve": ["-m", "orchestrator", "serve", "--data", "{data}"],
    "worker": ["-m", "orchestrator", "worker", "--once"],
    "agent": ["-m", "workers.agent", "--once"],
    "queue ls": ["-m", "orchestrator", "queue", "ls"],
}


@pytest.fixture(scope="module")
def broken_profile(tmp_path_factory):
    profile = init_secure(SecureInitConfig(directory=tmp_path_factory.mktemp("p") / "secure"))
    return profile


@pytest.mark.parametrize("name", COMMANDS)
def test_missing_key_file_refused_before_start(name, broken_profile, tmp_path):
    role = "orchestrator" if name == "serve" else "operator" if name == "queue ls" else "worker"
    config = broken_profile.configs[role]
    key = config.parent / f"{role}-key.pem"
    saved = key.read_bytes()
    key.unlink()
    try:
        argv = [a.format(data=tmp_path / "data") for a in COMMANDS[name]]
        proc = subprocess.run([sys.executable, *argv, "--zenoh-config", str(config)],
                              capture_output=True, text=True, timeout=120)
    finally:
        key.write_bytes(saved)
        key.chmod(0o600)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "missing" in lines[0] and key.name in lines[0], proc.stderr
    assert not (tmp_path / "data" / "catalog.sqlite").exists()
