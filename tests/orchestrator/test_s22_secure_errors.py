"""Secure mode's failures say what is wrong, in one line: a router that is not there, a certificate refused, a login
refused (Zenoh says "Unable to connect to any of [...]" for all of them), a role whose admin queries the ACL drops.

A real router process with a real `secure init` profile on loopback; the real commands, `serve` and `worker` in
their own processes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import json5
import pytest

from orchestrator.cli import main
from orchestrator.protocol import Keys
from orchestrator.acl import CLIENT_ROLES, client_role, roles_that_may_send
from orchestrator.secure import SecureInitConfig, SecureSet, cert_pem, init_secure, issue_certificate, key_pem, make_ca
from tests.conftest import free_port
from tests.orchestrator import test_secure
from tests.orchestrator.test_secure import REPO

#: The commands that open a session with a role's config: argv after ``python -m orchestrator``, and the role.
COMMANDS = {
    "serve": (["serve", "--init", "--data", "{data}"], "orchestrator"),
    "worker": (["worker", "--once"], "worker"),
    "stats": (["stats", "--timeout", "2"], "operator"),
    "queue ls": (["queue", "ls", "--timeout", "2"], "operator"),
}

secure_router = test_secure.secure_router  # one secure profile and its router, running, for this module too


def variant(secure: SecureSet, role: str, where: Path, change: Callable[[dict], None]) -> Path:
    """A copy of ``role``'s config at ``where``, changed by ``change``."""
    config = json5.loads(secure.configs[role].read_text())
    change(config)
    where.write_text(json.dumps(config))
    return where


def run_command(name: str, config: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    argv = [a.format(data=tmp_path / "data") for a in COMMANDS[name][0]]
    return subprocess.run([sys.executable, "-m", "orchestrator", *argv, "--zenoh-config", str(config)],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def one_line(stderr: str) -> str:
    """The one error line on ``stderr`` (log records aside: `serve` logs that it stopped)."""
    lines = [line for line in stderr.strip().splitlines() if line.startswith("activecollect")]
    assert len(lines) == 1, stderr
    return lines[0]


def wrong_password(config: dict) -> None:
    config["transport"]["auth"]["usrpwd"]["password"] += "x"


@pytest.mark.parametrize("name", COMMANDS)
def test_a_wrong_password_is_said_to_be_a_refused_login(secure_router, tmp_path, name):
    role = COMMANDS[name][1]
    config = variant(secure_router, role, tmp_path / "wrong.json5", wrong_password)
    done = run_command(name, config, tmp_path)
    assert done.returncode == 1, done.stderr
    line = one_line(done.stderr)
    endpoint = profile_endpoint(secure_router)
    assert (f"the router at {endpoint} accepted the TLS connection and this side's certificate but refused the "
            f"login: check the user ('{role}') and password in {config}") in line, line
    assert "Unable to connect" not in line


def profile_endpoint(secure: SecureSet) -> str:
    return json5.loads(secure.configs["worker"].read_text())["connect"]["endpoints"][0]


def test_an_unknown_user_is_said_to_be_a_refused_login(secure_router, tmp_path, capsys):
    def unknown(config: dict) -> None:
        config["transport"]["auth"]["usrpwd"]["user"] = "nobody"
    config = variant(secure_router, "operator", tmp_path / "unknown.json5", unknown)
    assert main(["stats", "--zenoh-config", str(config), "--timeout", "2"]) == 1
    line = one_line(capsys.readouterr().err)
    assert "refused the login: check the user ('nobody') and password" in line, line


def test_a_router_that_is_not_there_is_said_to_be_so(tmp_path, capsys):
    endpoint = f"tls/127.0.0.1:{free_port()}"  # nobody listens: no router started for this profile
    secure = init_secure(SecureInitConfig(tmp_path / "p", router_endpoint=endpoint))
    assert main(["stats", "--zenoh-config", str(secure.configs["operator"]), "--timeout", "2"]) == 1
    line = one_line(capsys.readouterr().err)
    assert f"nothing listens at {endpoint} (connection refused): is the router running there?" in line, line
    assert "login" not in line


def _foreign_pair(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A CA of another name than the profile's (one the start-up check leaves alone) and a `worker` certificate
    and key it signed: (ca, certificate, key)."""
    ca_key, ca = make_ca(common_name="another CA")
    key, cert = issue_certificate(ca_key, ca, "worker")
    paths = tmp_path / "other-ca.pem", tmp_path / "other-worker.pem", tmp_path / "other-worker-key.pem"
    for path, data in zip(paths, (cert_pem(ca), cert_pem(cert), key_pem(key))):
        path.write_bytes(data)
    return paths


def test_a_client_certificate_the_router_refuses_is_named(secure_router, tmp_path, capsys):
    _, cert, key = _foreign_pair(tmp_path)

    def foreign(config: dict) -> None:
        tls = config["transport"]["link"]["tls"]
        tls["connect_certificate"], tls["connect_private_key"] = str(cert), str(key)
    config = variant(secure_router, "worker", tmp_path / "foreign.json5", foreign)
    assert main(["stats", "--zenoh-config", str(config), "--timeout", "2"]) == 1
    line = one_line(capsys.readouterr().err)
    assert f"the router at {profile_endpoint(secure_router)} refused this side's certificate (" in line, line
    assert str(cert) in line and "login" not in line


def test_a_router_certificate_this_side_refuses_is_named(secure_router, tmp_path, capsys):
    ca, _, _ = _foreign_pair(tmp_path)

    def other_root(config: dict) -> None:
        config["transport"]["link"]["tls"]["root_ca_certificate"] = str(ca)
    config = variant(secure_router, "operator", tmp_path / "other-root.json5", other_root)
    assert main(["stats", "--zenoh-config", str(config), "--timeout", "2"]) == 1
    line = one_line(capsys.readouterr().err)
    assert f"the router at {profile_endpoint(secure_router)} presented a certificate this side does not accept" in line
    assert str(ca) in line, line


# ---------------------------------------------------------------- a role the ACL denies admin queries

@pytest.mark.parametrize("role", ["worker", "orchestrator"])
def test_an_operator_command_with_another_roles_config_names_the_role(secure_router, role, capsys):
    config = secure_router.configs[role]
    assert main(["stats", "--zenoh-config", str(config), "--timeout", "0.5"]) == 1
    line = one_line(capsys.readouterr().err)
    assert line.startswith("activecollect: no orchestrator answered on activecollect/admin/stats within 0.5 s")
    assert (f"{config} is the secure profile's {role} config, and the router's ACL drops admin queries from "
            f"every role but operator unanswered (give --zenoh-config {secure_router.configs['operator']})") in line, \
        line


def test_the_operators_own_config_says_no_service_answered(secure_router, capsys):
    assert main(["queue", "ls", "--zenoh-config", str(secure_router.configs["operator"]), "--timeout", "0.5"]) == 1
    line = one_line(capsys.readouterr().err)
    assert line.endswith("within 0.5 s (is `activecollect serve` running and reachable?)"), line


def test_roles_are_read_from_the_configs_secure_init_writes(secure_router):
    assert [client_role(json5.loads(secure_router.configs[r].read_text())) for r in CLIENT_ROLES] == list(CLIENT_ROLES)
    assert client_role(json5.loads(secure_router.configs["router"].read_text())) is None  # a router, not a client
    keys = Keys("lab")
    assert roles_that_may_send(keys.admin("stats"), "lab") == ("operator",)
    assert roles_that_may_send(keys.lease, "lab") == ("worker",)


@pytest.mark.parametrize("role", ["operator", "orchestrator"])
def test_a_worker_with_another_roles_config_exits_2_naming_the_role(secure_router, role, capsys):
    """Its lease queries would go unanswered for ever (the router's ACL drops them): it says so before it starts.
    (The old worker retried "lease: no reply" until stopped, never naming the config.)"""
    config = secure_router.configs[role]
    rc = main(["worker", "--once", "--zenoh-config", str(config)])
    line = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in line, line
    assert line == (f"activecollect worker: error: --zenoh-config: {config} is the secure profile's {role} config, "
                    "and the router's ACL drops lease queries from every role but worker unanswered "
                    f"(give --zenoh-config {secure_router.configs['worker']})"), line


@pytest.mark.parametrize("role", ["worker", "operator"])
def test_serve_with_another_roles_config_exits_2_naming_the_role(secure_router, role, tmp_path, capsys):
    """No request would ever reach its queryables (the router's ACL drops their declarations): it says so before
    anything starts, the data directory untouched."""
    config = secure_router.configs[role]
    rc = main(["serve", "--init", "--data", str(tmp_path / "data"), "--zenoh-config", str(config)])
    line = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in line, line
    assert line == (f"activecollect: error: --zenoh-config: {config} is the secure profile's {role} config, "
                    "and the router's ACL drops the declarations of the service's queryables from every role but "
                    f"orchestrator (give --zenoh-config {secure_router.configs['orchestrator']})"), line
    assert not (tmp_path / "data").exists()


# ---------------------------------------------------------------- a profile of another namespace

@pytest.mark.parametrize("argv, role, prefix", [
    (["worker", "--once"], "worker", "activecollect worker: error: --zenoh-config: "),
    (["serve", "--init", "--data", "DATA"], "orchestrator", "activecollect: error: --zenoh-config: "),
], ids=["worker", "serve"])
def test_a_command_given_another_namespace_than_its_profiles_exits_2_naming_it(secure_router, tmp_path, capsys,
                                                                                argv, role, prefix):
    """The profile records its namespace in each client config; its router's ACL drops every key of another one,
    so a --namespace typo would have had a worker wait for ever and a service serve nobody."""
    config = secure_router.configs[role]
    data = tmp_path / "data"
    argv = [str(data) if a == "DATA" else a for a in argv]
    rc = main([*argv, "--zenoh-config", str(config), "--namespace", "lab2"])
    line = capsys.readouterr().err.strip()
    assert rc == 2 and line == (f"{prefix}{config} is a secure profile of the namespace 'activecollect', whose "
                                "router's ACL drops every key of 'lab2': give --namespace activecollect (or a "
                                "profile made with secure init --namespace lab2)"), line
    assert not data.exists()


def test_an_operator_command_given_another_namespace_says_so_when_nobody_answers(secure_router, capsys):
    config = secure_router.configs["operator"]
    assert main(["stats", "--zenoh-config", str(config), "--namespace", "lab2", "--timeout", "0.5"]) == 1
    line = one_line(capsys.readouterr().err)
    assert line.startswith("activecollect: no orchestrator answered on lab2/admin/stats within 0.5 s, and none will: ")
    assert "is a secure profile of the namespace 'activecollect'" in line, line
