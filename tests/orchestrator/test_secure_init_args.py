"""`secure init` refuses what would make an unusable profile when the arguments are parsed (exit 2,
one line, nothing written), and a failure while it writes leaves no half-made directory behind."""

from __future__ import annotations

import datetime
import errno

import json5
import pytest
from cryptography import x509

import orchestrator.secure_files as secure_files
from orchestrator.secure import MAX_VALID_DAYS, SecureConfigError, SecureInitConfig, init_secure, planned_files
from tests.conftest import run_cli

BAD = [
    ("--valid-days", "10000000", "at most 36500 days"),
    ("--valid-days", str(MAX_VALID_DAYS + 1), "at most 36500 days"),
    ("--valid-days", "0", "positive integer"),
    ("--host", "", "DNS name or an IP address"),
    ("--host", "bad host name!", "DNS name or an IP address"),
    ("--host", "10.0.0.300", "DNS name or an IP address"),
    ("--host", "a..b", "DNS name or an IP address"),
    ("--host", "router.lan.", "DNS name or an IP address"),
    ("--host", "under_score.lan", "DNS name or an IP address"),
    ("--host", "x" * 64 + ".lan", "DNS name or an IP address"),
    ("--router-endpoint", "tls/bad host:7447", "DNS name or an IP address"),
    ("--router-endpoint", "tls/:7447", "tls/HOST:PORT"),
    ("--router-endpoint", "tcp/127.0.0.1:7447", "tls/HOST:PORT"),
    ("--router-endpoint", "tls/127.0.0.1:70000", "port must be 0-65535"),
    ("--router-endpoint", "tls/127.0.0.1:0", "1-65535"),
    ("--router-endpoint", "tls/::1:7447", "in brackets"),
    ("--router-endpoint", "tls/[router.lan]:7447", "brackets are for an IPv6 address"),
    ("--router-listen", "tls/bad host:7447", "DNS name or an IP address"),
    ("--router-listen", "tcp/0.0.0.0:7447", "tls/ADDR:PORT"),
]


@pytest.mark.parametrize("flag,value,expected", BAD, ids=[f"{f}={v[:20]}" for f, v, _ in BAD])
def test_a_bad_argument_exits_2_in_one_line_and_writes_nothing(capsys, tmp_path, flag, value, expected):
    directory = tmp_path / "new" / "profile"
    rc, out, err = run_cli(capsys, "secure", "init", str(directory), f"{flag}={value}")
    lines = err.strip().splitlines()
    assert rc == 2 and not out and len(lines) == 1, (rc, out, err)
    assert flag in lines[0] and expected.replace("ADDR", "HOST") in lines[0], lines[0]
    assert not (tmp_path / "new").exists()


def test_names_addresses_and_a_century_are_taken(capsys, tmp_path):
    directory = tmp_path / "p"
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--router-endpoint", "tls/[::1]:7447",
                         "--router-listen", "tls/[::]:7447", "--host", "router.lan", "--host", "10.0.0.5",
                         "--host", "fd00::5", "--host", "Router-2.Example.COM", "--valid-days", str(MAX_VALID_DAYS))
    assert rc == 0, err
    cert = x509.load_pem_x509_certificate((directory / "router.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {"router.lan", "Router-2.Example.COM"} <= set(san.get_values_for_type(x509.DNSName))
    assert {"::1", "10.0.0.5", "fd00::5"} <= {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}
    lifetime = cert.not_valid_after_utc - datetime.datetime.now(datetime.timezone.utc)
    assert MAX_VALID_DAYS - 1 <= lifetime.days <= MAX_VALID_DAYS


@pytest.mark.parametrize("change,match", [
    ({"extra_hosts": ("ok.lan", "not ok")}, "DNS name"),
    ({"valid_days": 10_000_000}, "valid_days"),
    ({"router_listen": "tls/bad host:7447"}, "router listen endpoint"),
])
def test_the_library_refuses_what_the_flags_refuse(tmp_path, change, match):
    with pytest.raises(SecureConfigError, match=match):
        SecureInitConfig(tmp_path / "p", **change)
    assert not (tmp_path / "p").exists()


def _disk_full_at(monkeypatch, call: int) -> None:
    """``init_secure``'s ``call``-th file write fails as on a full disk, after making its temporary file
    (as a write that fills the disk does); the ones before it are real."""
    real, calls = secure_files._stage, []

    def stage(path, data, secret):
        calls.append(path)
        tmp = real(path, data, secret)
        if len(calls) == call:
            raise OSError(errno.ENOSPC, "No space left on device")
        return tmp

    monkeypatch.setattr(secure_files, "_stage", stage)


def test_a_failed_write_removes_the_directories_it_made(capsys, monkeypatch, tmp_path):
    _disk_full_at(monkeypatch, 5)
    rc, out, err = run_cli(capsys, "secure", "init", str(tmp_path / "new" / "deeper" / "profile"))
    lines = err.strip().splitlines()
    assert rc == 1 and not out and len(lines) == 1 and "No space left on device" in lines[0], (rc, out, err)
    assert sorted(tmp_path.iterdir()) == []


def test_a_failed_write_into_an_existing_directory_leaves_it_and_no_temporary_files(monkeypatch, tmp_path):
    directory = tmp_path / "profile"
    directory.mkdir()
    _disk_full_at(monkeypatch, 3)
    with pytest.raises(OSError, match="No space left on device"):
        init_secure(SecureInitConfig(directory))
    assert directory.is_dir() and list(directory.iterdir()) == []  # not this call's to remove; nothing left in it
    monkeypatch.undo()
    first = init_secure(SecureInitConfig(directory))  # and a later init works there
    assert sorted(p.name for p in directory.iterdir()) == sorted(p.name for p in planned_files(directory))
    assert first.configs["worker"].is_file()


def test_a_forced_init_keeps_what_the_profile_was_made_for_unless_told_otherwise(capsys, tmp_path):
    """`secure init --force DIR` (README: how to add or rotate a credential) used to write the defaults' profile:
    namespace activecollect and a router certificate for 127.0.0.1 only, clients connecting to
    tls/127.0.0.1:7447, so every host's new files failed against the real router. The flags not given now keep
    the replaced profile's; the flags given win."""
    directory = tmp_path / "p"
    rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--namespace", "prod",
                           "--router-endpoint", "tls/ac.example.org:7447", "--router-listen", "tls/0.0.0.0:7447",
                           "--host", "10.0.0.5", "--host", "r2.lan")
    assert rc == 0, err
    # (the endpoint clients are given first: it printed only the listen address, which no client can use)
    assert "clients connect to the router at tls/ac.example.org:7447, listening on tls/0.0.0.0:7447" in out

    def made_with() -> tuple:
        worker = json5.loads((directory / "worker.json5").read_text())
        router = json5.loads((directory / "router.json5").read_text())
        cert = x509.load_pem_x509_certificate((directory / "router.pem").read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        names = {*san.get_values_for_type(x509.DNSName), *(str(ip) for ip in san.get_values_for_type(x509.IPAddress))}
        return (worker["metadata"]["activecollect_namespace"], worker["connect"]["endpoints"],
                router["listen"]["endpoints"], names)

    before = made_with()
    old_ca = (directory / "ca.pem").read_bytes()
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    assert rc == 0, err
    assert (directory / "ca.pem").read_bytes() != old_ca  # rotated
    assert made_with() == before, err
    assert "--namespace prod" in err and "--host 10.0.0.5" in err and "--host r2.lan" in err

    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--router-endpoint",
                         "tls/other.lan:7447", "--namespace", "staging")
    assert rc == 0, err
    namespace, connect, listen, names = made_with()
    assert (namespace, connect, listen) == ("staging", ["tls/other.lan:7447"], ["tls/0.0.0.0:7447"])
    assert {"other.lan", "10.0.0.5", "r2.lan"} <= names and "ac.example.org" not in names


def _namespace_and_endpoint(directory) -> tuple:
    worker = json5.loads((directory / "worker.json5").read_text())
    return worker["metadata"]["activecollect_namespace"], worker["connect"]["endpoints"]


def test_a_forced_init_keeps_the_namespace_of_a_profile_from_before_clients_recorded_it(capsys, tmp_path):
    """Profiles written before 6e5d02e carry no namespace metadata in their client configs; the router's ACL has
    it. A rotation of such a profile moved it to the default namespace, whose ACL denies the running service."""
    directory = tmp_path / "p"
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--namespace", "prod",
                         "--router-endpoint", "tls/ac.example.org:7447")
    assert rc == 0, err
    for role in ("orchestrator", "worker", "operator"):  # what the earlier release wrote: no metadata
        config = json5.loads((directory / f"{role}.json5").read_text())
        del config["metadata"]
        (directory / f"{role}.json5").write_text(json5.dumps(config))
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    assert rc == 0, err
    assert _namespace_and_endpoint(directory) == ("prod", ["tls/ac.example.org:7447"])
    assert "--namespace prod" in err


def test_the_force_that_finishes_a_rotation_cut_short_keeps_the_profile_set_aside(capsys, tmp_path):
    """A forced init killed between its folder renames leaves DIR missing and the old profile whole in
    .DIR.old-*; `secure init` then says to pass --force, which wrote the defaults' profile (127.0.0.1, namespace
    activecollect) and deleted the old one."""
    directory = tmp_path / "p"
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--namespace", "prod",
                         "--router-endpoint", "tls/ac.example.org:7447", "--host", "10.0.0.5")
    assert rc == 0, err
    directory.rename(tmp_path / ".p.old-0123abcd")  # what the crash leaves (secure_files._replace_folder)
    rc, _, err = run_cli(capsys, "secure", "init", str(directory))
    assert rc != 0 and "--force" in err
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    assert rc == 0, err
    assert _namespace_and_endpoint(directory) == ("prod", ["tls/ac.example.org:7447"])
    assert not (tmp_path / ".p.old-0123abcd").exists()


def test_a_forced_init_to_another_port_does_not_keep_a_bind_on_the_old_one(capsys, tmp_path):
    """--router-listen tls/0.0.0.0:7447 kept for --router-endpoint tls/HOST:7500: clients connect where the router
    does not listen. Refused, naming the flag to give."""
    directory = tmp_path / "p"
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--router-endpoint", "tls/ac.example.org:7447",
                         "--router-listen", "tls/0.0.0.0:7447")
    assert rc == 0, err
    before = (directory / "ca.pem").read_bytes()
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--router-endpoint",
                         "tls/ac.example.org:7500")
    assert rc == 2 and "--router-listen" in err, err
    assert (directory / "ca.pem").read_bytes() == before  # nothing written
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--router-endpoint",
                         "tls/ac.example.org:7500", "--router-listen", "tls/0.0.0.0:7500")
    assert rc == 0, err
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--router-endpoint",
                         "tls/other.example.org:7500")  # the same port: the bind is kept
    assert rc == 0 and "--router-listen tls/0.0.0.0:7500" in err, err


def test_the_force_that_finishes_a_rotation_cut_short_inside_the_folder_reads_the_old_profile_whole(capsys, tmp_path):
    """Inside a mount point the old files go into DIR/.old-* one by one, then the new ones come in one by one: a
    crash between two new ones leaves DIR with the new router.json5 and no client config. Read file by file, the
    settings mixed the old endpoint with the new profile's bind (clients at :7447, the router on :7500); the
    replaced profile is the one aside (a diff review's reproduction)."""
    directory, other = tmp_path / "p", tmp_path / "p2"
    for target, port in ((directory, 7447), (other, 7500)):
        rc, _, err = run_cli(capsys, "secure", "init", str(target), "--router-endpoint", f"tls/a.example.org:{port}",
                             "--router-listen", f"tls/0.0.0.0:{port}")
        assert rc == 0, err
    aside = directory / ".old-0123abcd"
    aside.mkdir()
    for path in [p for p in directory.iterdir() if p.is_file()]:
        path.rename(aside / path.name)
    for name in ("ca.pem", "router.pem", "router-key.pem", "router.json5"):  # (the new ones placed so far)
        (directory / name).write_bytes((other / name).read_bytes())
    rc, _, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    assert rc == 0, err
    router = json5.loads((directory / "router.json5").read_text())
    assert router["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
    assert _namespace_and_endpoint(directory)[1] == ["tls/a.example.org:7447"]
