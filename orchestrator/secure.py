"""The secure deployment profile: mutual TLS, user/password and a default-deny ACL.

Nothing here authenticates anyone. Zenoh does that from its own configuration;
this module writes that configuration (``secure init``) and refuses to start a
secure profile whose files are missing or unreadable (``validate_secure_config``).

Who is who: every role has its own certificate, signed by a private CA, whose
common name is the role name, and its own user/password. The router accepts
only TLS, requires a client certificate from that CA (mTLS) and checks the
password against its dictionary. Its ACL subjects match on both the
certificate's common name and the username, so a role's password alone, or
its certificate alone, is not enough to act as that role.
"""

from __future__ import annotations

import datetime
import functools
import ipaddress
import json
import os
import re
import secrets
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import json5
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from orchestrator import secure_files
from orchestrator.acl import DEFAULT_NAMESPACE, NAMESPACE_METADATA, ROLES, build_acl
from orchestrator.locators import endpoint_problem, split_endpoint
from orchestrator.protocol import Keys, ProtocolError
from orchestrator.transport import SecureConfigError, lookup_key

DEFAULT_ROUTER_ENDPOINT = "tls/127.0.0.1:7447"
#: Longest certificate lifetime ``secure init`` writes (a hundred years; far past it, dates overflow).
MAX_VALID_DAYS = 36500
#: One label of a DNS name (RFC 1123): letters, digits and inner hyphens, at most 63 characters.
_DNS_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def host_problem(host: str) -> str:
    """What keeps ``host`` from naming the router in its certificate ('' when nothing): it must be
    an IP address or a DNS name (dot-separated labels of letters, digits and inner hyphens)."""
    try:
        ipaddress.ip_address(host)
        return ""
    except ValueError:
        pass  # not an address: a name, then
    labels = host.split(".")  # (no trailing dot either: a certificate names the host without one)
    if (not host or len(host) > 253 or not all(_DNS_LABEL.fullmatch(label) for label in labels)
            or labels[-1].isdigit()):  # (an all-digit last label is a mistyped address such as 10.0.0.300)
        return f"expected a DNS name or an IP address, found {host!r}"
    return ""


def tls_endpoint(endpoint: str, what: str = "router endpoint") -> tuple[str, int]:
    """(HOST, PORT) of a ``tls/HOST:PORT`` endpoint, brackets removed from an IPv6 HOST: its shape
    checked as ``orchestrator.endpoints`` checks every endpoint, its HOST as ``host_problem``.

    Raises SecureConfigError naming ``what`` when it is not one.
    """
    if problem := endpoint_problem(endpoint):
        raise SecureConfigError(f"expected a {what} like tls/HOST:PORT: {problem}")
    if not endpoint.startswith("tls/"):
        raise SecureConfigError(f"expected a {what} like tls/HOST:PORT, found {endpoint!r}")
    _, _, host, port = split_endpoint(endpoint)
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
        if ":" not in host:
            raise SecureConfigError(f"{what} {endpoint!r}: brackets are for an IPv6 address, found {host!r}")
    elif ":" in host:
        raise SecureConfigError(f"{what} {endpoint!r}: an IPv6 address goes in brackets, as in tls/[::1]:7447")
    if problem := host_problem(host):
        raise SecureConfigError(f"{what} {endpoint!r}: {problem}")
    return host, int(port)


def router_endpoint_host(endpoint: str) -> str:
    """The HOST of a router endpoint clients connect to, ``tls/HOST:PORT`` (``tls_endpoint``) with a port
    other than 0. Raises SecureConfigError when it is not one."""
    host, port = tls_endpoint(endpoint)
    if port == 0:
        raise SecureConfigError(f"expected a router endpoint like tls/HOST:PORT with a port clients can "
                                f"connect to (1-65535), found {endpoint!r}")
    return host


@dataclass
class SecureInitConfig:
    """What ``activecollect secure init`` writes."""

    directory: Path
    """Where the configs, certificates and credentials go (created 0700)."""
    namespace: str = DEFAULT_NAMESPACE
    """Key namespace the ACL protects (NS/orch/**, NS/admin/**, NS/workers/**, NS/events/**)."""
    router_endpoint: str = DEFAULT_ROUTER_ENDPOINT
    """tls/HOST:PORT the router listens on and the clients connect to."""
    router_listen: str | None = None
    """Endpoint the router binds (e.g. tls/0.0.0.0:7447); defaults to router_endpoint."""
    extra_hosts: tuple[str, ...] = ()
    """More names/addresses put in the router certificate (other ways clients reach it)."""
    force: bool = False
    """Overwrite an existing set (new CA, new passwords: every host needs the new files)."""
    valid_days: int = 825
    """Certificate lifetime."""

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)
        try:
            Keys(self.namespace)
        except ProtocolError as exc:
            raise SecureConfigError(exc.message) from exc
        self.router_host()  # validates router_endpoint
        if self.router_listen is not None:
            tls_endpoint(self.router_listen, "router listen endpoint")
        for host in self.extra_hosts:
            if problem := host_problem(host):
                raise SecureConfigError(f"router host: {problem}")
        if not 0 < self.valid_days <= MAX_VALID_DAYS:
            raise SecureConfigError(f"expected valid_days in 1..{MAX_VALID_DAYS}, found {self.valid_days}")

    def router_host(self) -> str:
        """The HOST of ``router_endpoint`` (``router_endpoint_host``)."""
        return router_endpoint_host(self.router_endpoint)


@dataclass
class SecureSet:
    """Paths of what ``init_secure`` wrote."""

    directory: Path
    """The directory itself."""
    configs: dict[str, Path] = field(default_factory=dict)
    """role -> Zenoh JSON5 config."""
    credentials: dict[str, tuple[str, str]] = field(default_factory=dict)
    """role -> (user, password)."""
    ca_certificate: Path | None = None
    """The private CA's certificate (the CA's key is not kept)."""
    left_over: Path | None = None
    """Where the profile ``force`` replaced is left when it could not be deleted after (it holds the old keys)."""


# ---------------------------------------------------------------- certificates

def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "activecollect"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _san(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def make_ca(common_name: str = "activecollect CA", valid_days: int = 825
            ) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A fresh self-signed CA (ECDSA P-256) that may sign end-entity certificates only."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(_name(common_name)).issuer_name(_name(common_name))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=valid_days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return key, cert


def issue_certificate(ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate,
                      common_name: str, hosts: tuple[str, ...] = (), valid_days: int = 825
                      ) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate for one role, usable as TLS client and server; CN = ``common_name``.

    ``hosts`` become subject alternative names (a client checks the router's name against
    them); a certificate without hosts still carries its CN as a DNS name, since some TLS
    stacks refuse end-entity certificates without any SAN.
    """
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    names = [_san(h) for h in dict.fromkeys((*hosts, common_name))]
    cert = (x509.CertificateBuilder()
            .subject_name(_name(common_name)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=valid_days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    return key, cert


def cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


# ---------------------------------------------------------------- configs

def _tls(directory: Path, role: str, listen: bool) -> dict[str, Any]:
    cert, key = str(directory / f"{role}.pem"), str(directory / f"{role}-key.pem")
    tls: dict[str, Any] = {"root_ca_certificate": str(directory / "ca.pem"),
                           "connect_certificate": cert, "connect_private_key": key,
                           "enable_mtls": True, "verify_name_on_connect": True}
    if listen:
        tls.update(listen_certificate=cert, listen_private_key=key)
    return tls


def router_config(cfg: SecureInitConfig, password: str) -> dict[str, Any]:
    """Zenoh config of the router: TLS only, client certificates required, passwords checked, ACL.

    The router's own user/password is what it presents when linked (``--connect``) to another
    site's router built from the same profile.
    """
    d = cfg.directory.resolve()
    return {
        "mode": "router",
        "listen": {"endpoints": [cfg.router_listen or cfg.router_endpoint]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {"protocols": ["tls"], "tls": _tls(d, "router", listen=True)},
            "auth": {"usrpwd": {"user": "router", "password": password,
                                "dictionary_file": str(d / "users.txt")}},
        },
        "access_control": build_acl(cfg.namespace),
    }


def client_config(cfg: SecureInitConfig, role: str, password: str) -> dict[str, Any]:
    """Zenoh config of one client role: connects to the router over mutual TLS with its password."""
    d = cfg.directory.resolve()
    return {
        "mode": "client",
        "connect": {"endpoints": [cfg.router_endpoint]},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {"protocols": ["tls"], "tls": _tls(d, role, listen=False)},
            "auth": {"usrpwd": {"user": role, "password": password}},
        },
        # Zenoh keeps metadata as it is; the commands given this config check their --namespace against it
        # (``acl.denied_by_acl``): the router's ACL lets this profile's keys through and drops any other's.
        "metadata": {NAMESPACE_METADATA: cfg.namespace},
    }


def _json5_text(role: str, cfg: SecureInitConfig, body: dict[str, Any]) -> str:
    header = (f"// activecollect secure profile: {role} (namespace {cfg.namespace!r}).\n"
              f"// Zenoh's own config format; pass it with --zenoh-config. Written by "
              f"`activecollect secure init`.\n"
              f"// Holds this role's password: keep it private (0600).\n")
    return header + json.dumps(body, indent=2) + "\n"


#: The names every router certificate carries besides the router's own host: it also serves clients on its host.
_LOCAL_ROUTER_NAMES = ("localhost", "127.0.0.1")


def profile_settings(directory: Path) -> dict[str, Any]:
    """What the secure profile in ``directory`` was made with, under ``SecureInitConfig``'s field names:
    ``namespace`` (profiles from before it was recorded have none), ``router_endpoint``, ``router_listen`` (None
    where the router binds the endpoint) and ``extra_hosts`` (the router certificate's names beyond those every
    profile has). Each one it cannot read is left out; {} where no profile is there. ``secure init --force``
    keeps them for the flags not given: a rotation must not move a profile to the defaults' 127.0.0.1."""
    found: dict[str, Any] = {}
    file = functools.partial(_profile_file, directory)
    try:
        client = json5.loads(file("orchestrator.json5").read_text())
        endpoints = lookup_key(client, "connect/endpoints") or []
        if endpoints:
            found["router_endpoint"] = str(endpoints[0])
        namespace = (client.get("metadata") or {}).get(NAMESPACE_METADATA)
        if namespace:
            found["namespace"] = str(namespace)
    except (OSError, ValueError, AttributeError):
        pass
    try:
        router = json5.loads(file("router.json5").read_text())
        if "namespace" not in found:  # a profile from before the clients recorded it: the ACL's link rule has it
            link = [r for r in lookup_key(router, "access_control/rules") or [] if r.get("id") == "router-link"]
            keys = link[0].get("key_exprs") or [] if link else []
            if keys and str(keys[0]).endswith("/**"):
                found["namespace"] = str(keys[0])[:-len("/**")]
        listen = lookup_key(router, "listen/endpoints") or []
        if listen and "router_endpoint" in found:
            found["router_listen"] = None if listen[0] == found["router_endpoint"] else str(listen[0])
    except (OSError, ValueError, AttributeError):
        pass
    try:
        cert = x509.load_pem_x509_certificate(file("router.pem").read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        names = [*san.get_values_for_type(x509.DNSName), *(str(ip) for ip in san.get_values_for_type(x509.IPAddress))]
        usual = {*_LOCAL_ROUTER_NAMES, "router"}  # (and its common name)
        if "router_endpoint" in found:
            usual.add(router_endpoint_host(found["router_endpoint"]).strip("[]"))
        found["extra_hosts"] = tuple(n for n in names if n not in usual)
    except (OSError, ValueError, x509.ExtensionNotFound, SecureConfigError):
        pass
    return found


def _profile_file(directory: Path, name: str) -> Path:
    """``directory / name``, or where a forced init that a crash cut short left the replaced profile's copy of it
    (a ``.NAME.old-*`` folder beside ``directory``, which may then be missing, or a ``.old-*`` folder inside it):
    the profile ``secure init --force`` replaces then, and reads the settings of."""
    path = directory / name
    if all(p.exists() for p in planned_files(directory)):  # whole: a forced init cut short left none of it
        return path
    # one cut short inside ``directory`` (a mount point) moved every old file into ``.old-*`` before the first new
    # one came in: a file of ``directory`` may be the new profile's, the copy aside is the replaced one's
    aside = [*secure_files.sibling_swaps(directory),
             *(secure_files.interrupted_swaps(directory) if directory.is_dir() else [])]
    copies = [f / name for f in aside if ".old-" in f.name and (f / name).is_file()]
    return max(copies, key=lambda c: c.stat().st_mtime) if copies else path  # (DIR's own: an old one not yet moved)


def planned_files(directory: Path) -> list[Path]:
    """Every file ``init_secure`` writes into ``directory``."""
    names = ["ca.pem", "users.txt"]
    for role in ROLES:
        names += [f"{role}.json5", f"{role}.pem", f"{role}-key.pem"]
    return [directory / n for n in names]


def _render(cfg: SecureInitConfig) -> tuple[SecureSet, dict[Path, tuple[bytes, bool]]]:
    """The whole profile in memory: what ``init_secure`` returns, and each file's bytes and secrecy."""
    d = cfg.directory
    out = SecureSet(directory=d, ca_certificate=d / "ca.pem")
    ca_key, ca_cert = make_ca(valid_days=cfg.valid_days)
    files: dict[Path, tuple[bytes, bool]] = {d / "ca.pem": (cert_pem(ca_cert), False)}
    router_hosts = (cfg.router_host(), *cfg.extra_hosts, *_LOCAL_ROUTER_NAMES)
    for role in ROLES:
        key, cert = issue_certificate(ca_key, ca_cert, role,
                                      hosts=router_hosts if role == "router" else (),
                                      valid_days=cfg.valid_days)
        files[d / f"{role}.pem"] = (cert_pem(cert), False)
        files[d / f"{role}-key.pem"] = (key_pem(key), True)
    del ca_key  # not kept: a new role certificate means a new `secure init --force`
    out.credentials = {role: (role, secrets.token_urlsafe(24)) for role in ROLES}
    users = "".join(f"{user}:{password}\n" for user, password in out.credentials.values())
    files[d / "users.txt"] = (users.encode(), True)
    for role in ROLES:
        password = out.credentials[role][1]
        body = router_config(cfg, password) if role == "router" else client_config(cfg, role, password)
        out.configs[role] = d / f"{role}.json5"
        files[out.configs[role]] = (_json5_text(role, cfg, body).encode(), True)
    return out, files


def init_secure(cfg: SecureInitConfig) -> SecureSet:
    """Writes a ready secure profile: CA, per-role certificates and passwords, four Zenoh configs.

    All or nothing: every file is made first, staged under a temporary name, and only then put in
    place; when anything fails, what this call made (staged files, files put in place, directories) is
    removed again. A profile that ``force`` replaces is swapped whole (``secure_files.replace``): a failure leaves the
    old one, never old and new files mixed; so does a profile whose swap a crash cut short (its ``.new-*`` /
    ``.old-*`` folders deleted then). Raises SecureConfigError when the directory already holds a profile
    and ``force`` is off, or when it cannot be created; OSError when a file cannot be written (a full disk).
    """
    directory = cfg.directory.resolve()  # where a link points (a dangling one too: made there, not at the link)
    planned = planned_files(directory)
    swaps: list[Path] = []
    beside = secure_files.sibling_swaps(directory)
    if beside and not cfg.force:
        raise SecureConfigError(_cut_short(directory, beside))
    if directory.is_dir():  # it becomes 0700: never take over a directory holding other things
        _refuse_foreign(directory)
        swaps = secure_files.interrupted_swaps(directory)
        ours = set(planned) | set(swaps) | secure_files.staged_names(planned)  # (a first init killed midway)
        others = sorted(p.name for p in directory.iterdir() if p not in ours)
        if others:
            raise SecureConfigError(f"expected an empty directory or a secure profile at {directory}, "
                                    f"found other files ({', '.join(others[:3])})")
    existing = [p for p in planned if p.exists()]
    if swaps and not cfg.force:
        raise SecureConfigError(f"{directory} holds a secure profile whose replacement was cut short: the old "
                                f"files set aside and the new ones not yet in place are in "
                                f"{', '.join(p.name for p in swaps)}; pass --force to replace it whole (and delete "
                                "those)")
    if existing and not cfg.force:
        raise SecureConfigError(f"{directory} already holds a secure profile "
                                f"({existing[0].name}, ...); pass --force to replace it")
    out, files = _render(cfg)  # before anything touches the disk
    if existing or swaps:
        out.left_over = secure_files.replace(directory, files)
    else:
        secure_files.write_new(directory, files)
    secure_files.delete_swaps(beside)
    return out


def _refuse_foreign(directory: Path) -> None:
    """A directory another user owns is never made a profile's: its owner could swap the files in it (a CA, a
    config without an ACL) after they were checked."""
    owner = directory.stat().st_uid
    if owner != os.geteuid():
        raise SecureConfigError(f"{directory} is owned by uid {owner}, not by this user (uid {os.geteuid()}): a "
                                "secure profile's directory must be its user's own, or its owner could swap the "
                                "files in it")


def _cut_short(directory: Path, beside: list[Path]) -> str:
    """Why ``init_secure`` stops where an earlier forced init was killed between its folder renames."""
    old = [p for p in beside if ".old-" in p.name]
    if not directory.exists() and old:
        return (f"the replacement of the secure profile in {directory} was cut short: the old profile is whole in "
                f"{old[-1]} (rename it back to {directory.name} to keep it), the new one was not put in place; "
                f"pass --force to write a new profile and delete {', '.join(p.name for p in beside)}")
    return (f"a replacement of the secure profile in {directory} was cut short and left "
            f"{', '.join(p.name for p in beside)} beside it (files with keys and passwords); pass --force to "
            "replace the profile and delete them")


# ---------------------------------------------------------------- start-up check

def is_secure_profile(path: str | os.PathLike[str]) -> bool:
    """True when the config only allows TLS links (what ``secure init`` writes)."""
    config = json5.loads(Path(path).read_text())
    return lookup_key(config, "transport/link/protocols") == ["tls"]


def private_mode_ok(path: Path) -> bool:
    """True when nobody but the owner can read ``path`` (0600 or narrower)."""
    return stat.S_IMODE(path.stat().st_mode) & 0o077 == 0
