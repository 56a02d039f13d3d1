"""Certificates a TLS handshake would refuse are named at start-up in one line, not left to "Unable to connect".

Zenoh says the same "Unable to connect to any of [...]" for an expired certificate, a key that is not the
certificate's, and files of two ``secure init`` runs mixed on one host (what redistributing a rotated profile
by hand leads to); every process given ``--zenoh-config`` checks its files first (``validate_secure_config``).
"""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
from pathlib import Path

import json5
import pytest
from cryptography import x509

from orchestrator.cli import main
from orchestrator.secure import SecureInitConfig, SecureSet, cert_pem, init_secure, issue_certificate, key_pem, make_ca
from orchestrator.transport import SecureConfigError, validate_secure_config
from tests.orchestrator.test_secure import REPO

TLS = ("transport", "link", "tls")
DAY = datetime.timedelta(days=1)


@pytest.fixture(scope="module")
def profiles(tmp_path_factory) -> tuple[SecureSet, SecureSet]:
    """Two profiles of two `secure init` runs: their CAs have the same name and different keys."""
    root = tmp_path_factory.mktemp("profiles")
    return init_secure(SecureInitConfig(root / "new")), init_secure(SecureInitConfig(root / "old"))


def with_tls(profile: SecureSet, role: str, path: Path, **files: Path) -> Path:
    """``role``'s config of ``profile`` with some of its TLS files replaced, written to ``path``."""
    config = json5.loads(profile.configs[role].read_text())
    tls = config
    for part in TLS:
        tls = tls[part]
    tls.update({key: str(value) for key, value in files.items()})
    path.write_text(json.dumps(config))
    return path


def dated_pair(directory: Path, start: datetime.datetime, end: datetime.datetime, ca_name: str = "activecollect CA"
               ) -> dict[str, Path]:
    """A CA and a `worker` certificate it signed, valid from ``start`` to ``end``: the TLS files of a config."""
    ca_key, ca = make_ca(common_name=ca_name)
    key, cert = issue_certificate(ca_key, ca, "worker")
    dated = (x509.CertificateBuilder().subject_name(cert.subject).issuer_name(ca.subject)
             .public_key(key.public_key()).serial_number(x509.random_serial_number())
             .not_valid_before(start).not_valid_after(end).sign(ca_key, cert.signature_hash_algorithm))
    directory.mkdir()
    files = {"root_ca_certificate": (directory / "ca.pem", cert_pem(ca)),
             "connect_certificate": (directory / "worker.pem", cert_pem(dated)),
             "connect_private_key": (directory / "worker-key.pem", key_pem(key))}
    for path, data in files.values():
        path.write_bytes(data)
    return {name: path for name, (path, _) in files.items()}


def broken(kind: str, profiles: tuple[SecureSet, SecureSet], tmp_path: Path) -> tuple[Path, str]:
    """A worker config broken in one way, and the words its refusal must hold."""
    new, old = profiles
    now = datetime.datetime.now(datetime.timezone.utc)
    config = tmp_path / f"{kind}.json5"
    if kind == "expired":
        return with_tls(new, "worker", config, **dated_pair(tmp_path / "d", now - 10 * DAY, now - DAY)), "expired on"
    if kind == "not_yet_valid":
        return (with_tls(new, "worker", config, **dated_pair(tmp_path / "d", now + DAY, now + 10 * DAY)),
                "is not valid before")
    if kind == "other_run":  # the new CA, this host's old certificate and key
        return (with_tls(new, "worker", config, connect_certificate=old.directory / "worker.pem",
                         connect_private_key=old.directory / "worker-key.pem"), "is not signed by the CA in")
    if kind == "other_key":  # the new certificate, the old key
        return (with_tls(new, "worker", config, connect_private_key=old.directory / "worker-key.pem"),
                "is not the key of")
    assert kind == "not_a_key"
    return with_tls(new, "worker", config, connect_private_key=new.directory / "worker.pem"), "no readable"


KINDS = ("expired", "not_yet_valid", "other_run", "other_key", "not_a_key")


@pytest.mark.parametrize("kind", KINDS)
def test_secure_check_names_a_certificate_tls_would_refuse(kind, profiles, tmp_path, capsys):
    config, words = broken(kind, profiles, tmp_path)
    with pytest.raises(SecureConfigError, match=words):
        validate_secure_config(config)
    assert main(["secure", "check", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and str(config) in err[0], err


def test_sound_certificates_pass_also_from_a_ca_of_another_name(profiles, tmp_path):
    """Not over-eager: each written config passes, and so does a certificate whose issuer is not in the CA file
    (another CA, or a chain, may vouch for it: only the router knows)."""
    new, _ = profiles
    for role in new.configs:
        assert validate_secure_config(new.configs[role])
    now = datetime.datetime.now(datetime.timezone.utc)
    other = dated_pair(tmp_path / "d", now - DAY, now + DAY, ca_name="another CA")
    config = with_tls(new, "worker", tmp_path / "w.json5", connect_certificate=other["connect_certificate"],
                      connect_private_key=other["connect_private_key"])
    assert validate_secure_config(config)


@pytest.mark.parametrize("command", [["-m", "workers.agent", "--once"], ["-m", "orchestrator", "router"]])
def test_a_process_given_mixed_profile_files_exits_2_in_one_line(command, profiles, tmp_path):
    """The worker agent and the router refuse to start (before, the worker said "Unable to connect", exit 1, and
    the router started, refusing every client's handshake)."""
    new, old = profiles
    role = "router" if "router" in command else "worker"
    config = with_tls(new, role, tmp_path / f"{role}.json5", root_ca_certificate=old.directory / "ca.pem")
    done = subprocess.run([sys.executable, *command, "--zenoh-config", str(config)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert len(lines) == 1 and "is not signed by the CA in" in lines[0] and str(old.directory / "ca.pem") in lines[0]
