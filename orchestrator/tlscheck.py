"""The certificates of a secure profile checked as a TLS handshake would check them (``transport``'s
``validate_secure_config`` calls ``check`` when a config names TLS files; imported only then: ``cryptography``
costs a worker ~8 MiB).

What Zenoh says only as "Unable to connect" after the handshake, said before it in one line: certificates past
their dates (all in the CA file), a key that is not its certificate's, a certificate naming the CA as its issuer
but not signed by it (files of two ``secure init`` runs). One from a CA of another name is left alone.
"""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any, Callable

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from orchestrator.transport import SecureConfigError, lookup_key

_TLS = "transport/link/tls/"  # and next: (certificate, its private key) presented when listening, when connecting
_TLS_PAIRS = tuple((f"{_TLS}{side}_certificate", f"{_TLS}{side}_private_key") for side in ("listen", "connect"))


def check(config_path: Path, config: dict[str, Any]) -> None:
    """Raises SecureConfigError naming the config, the key and the file of the first problem (see the module)."""
    now = datetime.datetime.now(datetime.timezone.utc)
    ca_path = lookup_key(config, _TLS + "root_ca_certificate")
    cas = _read_pem(config_path, _TLS + "root_ca_certificate", ca_path) if ca_path else []
    if cas and all(_dates_problem(ca, now) for ca in cas):
        raise SecureConfigError(f"{config_path}: {_TLS}root_ca_certificate -> {ca_path} {_dates_problem(cas[0], now)}")
    for cert_key, key_key in _TLS_PAIRS:
        cert_path, key_path = lookup_key(config, cert_key), lookup_key(config, key_key)
        if not cert_path:
            continue
        what = f"{config_path}: {cert_key} -> {cert_path}"
        cert = _read_pem(config_path, cert_key, cert_path)[0]  # the leaf; its chain may follow it
        if problem := _dates_problem(cert, now):
            raise SecureConfigError(f"{what} {problem}")
        named = [ca for ca in cas if ca.subject == cert.issuer]
        if named and not any(_signed_by(cert, ca) for ca in named):
            raise SecureConfigError(f"{what} is not signed by the CA in {ca_path}, which has its issuer's name (files "
                                    f"of two `secure init` runs mixed? copy this role's files again)")
        if key_path and _read_pem(config_path, key_key, key_path, _public_of_key) != _spki(cert.public_key()):
            raise SecureConfigError(f"{config_path}: {key_key} -> {key_path} is not the key of {cert_path}")


def _read_pem(config_path: Path, key: str, value: str,
              load: Callable[[bytes], Any] = x509.load_pem_x509_certificates) -> Any:
    try:
        return load(Path(value).expanduser().read_bytes())
    except (ValueError, TypeError):  # TypeError: an encrypted key, which Zenoh cannot read either
        raise SecureConfigError(f"{config_path}: {key} -> {value} holds no readable (unencrypted) PEM "
                                f"{'key' if key.endswith('_key') else 'certificate'}") from None


def _dates_problem(cert: x509.Certificate, now: datetime.datetime) -> str:  # ('' when valid)
    if now > cert.not_valid_after_utc:
        return f"expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC (`secure init --force` renews a profile)"
    if now < cert.not_valid_before_utc:
        return f"is not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (is this host's clock right?)"
    return ""


def _signed_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def _public_of_key(pem: bytes) -> bytes:
    return _spki(serialization.load_pem_private_key(pem, password=None).public_key())


def _spki(public_key: Any) -> bytes:
    return public_key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
