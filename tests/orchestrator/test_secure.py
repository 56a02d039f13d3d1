"""The secure profile: what `secure init` writes, the start-up check, and Zenoh enforcing it.

A real router process (orchestrator.router with the profile's router.json5), the real service
and worker agent, and real client sessions, all on loopback. Zenoh denials are silent, so every denial is
asserted by absence within a window, right after a positive control in the same test proved the path works.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import json5
import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from orchestrator.cli import main
from orchestrator.protocol import Keys
from orchestrator.acl import CLIENT_ROLES, ROLES, build_acl
from orchestrator.secure import SecureConfigError, SecureInitConfig, SecureSet, init_secure, private_mode_ok
from orchestrator.transport import validate_secure_config
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage.requests import RequestStatus
from tests.conftest import free_port, wait_for

REPO = Path(__file__).resolve().parents[2]
NS = "activecollect"
KEYS = Keys(NS)
ABSENT_WINDOW = 1.0  # how long a denied message gets to (not) show up, after a positive control


# ---------------------------------------------------------------- helpers (also used by the router
# and partition tests)


def stays_false(predicate: Callable[[], object], window: float = ABSENT_WINDOW) -> bool:
    """True when ``predicate`` never holds during ``window`` seconds (absence of a denied message)."""
    deadline = time.monotonic() + window
    while time.monotonic() < deadline:
        if predicate():
            return False
        time.sleep(0.05)
    return not predicate()


class Proc:
    """A child process whose output lines are collected by a thread (so waits have deadlines)."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None) -> None:
        self.argv = argv
        self.popen = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      cwd=REPO, env={**os.environ, **(env or {})})
        self.lines: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_line(self, needle: str, timeout: float = 30.0) -> str:
        def found() -> str | None:
            hit = next((line for line in self.lines if needle in line), None)
            if hit is None and self.popen.poll() is not None:
                raise AssertionError(f"{self.argv} exited {self.popen.returncode} before printing "
                                     f"{needle!r}: {self.output()}")
            return hit
        return wait_for(found, timeout, f"{needle!r} from {' '.join(self.argv)[-120:]}")

    def started(self, needle: str = "listening on") -> Proc:
        """Wait for ``needle`` in the output; stop the process if it never comes. Returns self."""
        try:
            self.wait_line(needle)
        except AssertionError:
            self.stop()
            raise
        return self

    def output(self) -> str:
        return "\n".join(self.lines)[-2000:]

    def stop(self, timeout: float = 15.0) -> int:
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout)
        return self.popen.returncode


def activecollect(*args: str, prefix: tuple[str, ...] = ()) -> list[str]:
    return [*prefix, sys.executable, "-m", "orchestrator", *args]


#: The router, run through orchestrator.router directly: these tests are about the profile, and
#: test_router.py covers the `activecollect router` command. argv: CONFIG LISTEN-JSON CONNECT-JSON
ROUTER = """
import json, sys
from pathlib import Path
from orchestrator.router import RouterConfig, run_router
cfg = RouterConfig(zenoh_config=Path(sys.argv[1]), listen=json.loads(sys.argv[2]), connect=json.loads(sys.argv[3]))
sys.exit(run_router(cfg, out=sys.stdout))
"""


def start_router(config: Path, listen: tuple[str, ...] = (), connect: tuple[str, ...] = (),
                 prefix: tuple[str, ...] = ()) -> Proc:
    return Proc([*prefix, sys.executable, "-c", ROUTER, str(config), json.dumps(listen), json.dumps(connect)]).started()


def role_config(secure: SecureSet, role: str, mutate: Callable[[dict], None] | None = None) -> zenoh.Config:
    cfg = json5.loads(secure.configs[role].read_text())
    if mutate is not None:
        mutate(cfg)
    return zenoh.Config.from_json5(json.dumps(cfg))


def open_role(secure: SecureSet, role: str, mutate: Callable[[dict], None] | None = None) -> zenoh.Session:
    return zenoh.open(role_config(secure, role, mutate))


def get_payloads(session: zenoh.Session, key: str, timeout: float = 2.0) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, timeout=timeout) if r.ok is not None]


# ---------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def secure_router(tmp_path_factory):
    """One secure profile and its router process, shared by this module's network tests."""
    directory = tmp_path_factory.mktemp("secure") / "profile"
    secure = init_secure(SecureInitConfig(directory, router_endpoint=f"tls/127.0.0.1:{free_port()}"))
    router = start_router(secure.configs["router"])
    yield secure
    assert router.stop() == 0, router.output()


@pytest.fixture()
def sessions():
    """Sessions and declared entities a test opened; closed (or undeclared) afterwards, newest first."""
    opened: list = []
    yield opened
    for entity in reversed(opened):
        if isinstance(entity, zenoh.Session):
            entity.close()
        else:
            entity.undeclare()


# ---------------------------------------------------------------- what init writes

def test_init_writes_private_profile_with_role_certificates(tmp_path):
    directory = tmp_path / "profile"
    secure = init_secure(SecureInitConfig(directory, namespace="site-a",
                                          router_endpoint="tls/10.0.0.5:7447", extra_hosts=("router.lan",)))
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700
    assert set(secure.configs) == set(ROLES)
    secrets_ = [directory / "users.txt", *secure.configs.values(),
                *(directory / f"{role}-key.pem" for role in ROLES)]
    assert all(private_mode_ok(p) for p in secrets_), [oct(p.stat().st_mode) for p in secrets_]
    ca = x509.load_pem_x509_certificate((directory / "ca.pem").read_bytes())
    for role in ROLES:
        cert = x509.load_pem_x509_certificate((directory / f"{role}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        cert.verify_directly_issued_by(ca)
    router_cert = x509.load_pem_x509_certificate((directory / "router.pem").read_bytes())
    san = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "router.lan" in san.get_values_for_type(x509.DNSName)
    assert "10.0.0.5" in [str(ip) for ip in san.get_values_for_type(x509.IPAddress)]
    # every config is one Zenoh accepts (it refuses unknown keys), TLS only, no plaintext listener
    for role, path in secure.configs.items():
        zenoh.Config.from_file(str(path))
        cfg = json5.loads(path.read_text())
        assert cfg["transport"]["link"]["protocols"] == ["tls"]
        assert all(ep.startswith("tls/") for ep in cfg["listen"]["endpoints"] + cfg["connect"]["endpoints"])
    users = dict(line.split(":", 1) for line in (directory / "users.txt").read_text().split())
    for role in CLIENT_ROLES:
        usrpwd = json5.loads(secure.configs[role].read_text())["transport"]["auth"]["usrpwd"]
        assert users[role] == usrpwd["password"] and usrpwd["user"] == role
    assert len(set(users.values())) == len(ROLES)


def test_init_cli_writes_a_profile_and_refuses_a_second_without_force(tmp_path, capsys):
    argv = ["secure", "init", str(tmp_path / "p"), "--namespace", "lab", "--router-endpoint",
            "tls/127.0.0.1:7999", "--json"]
    assert main(argv) == 0
    configs = json.loads(capsys.readouterr().out)["configs"]
    assert sorted(configs) == sorted(ROLES)
    assert validate_secure_config(configs["worker"])
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--force" in err[0]


def test_init_refuses_to_overwrite_without_force(tmp_path):
    first = init_secure(SecureInitConfig(tmp_path / "p"))
    with pytest.raises(SecureConfigError, match="--force"):
        init_secure(SecureInitConfig(tmp_path / "p"))
    second = init_secure(SecureInitConfig(tmp_path / "p", force=True))
    assert second.credentials["worker"] != first.credentials["worker"]


def test_init_refuses_a_directory_holding_other_files(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(SecureConfigError, match="notes.txt"):
        init_secure(SecureInitConfig(tmp_path, force=True))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize("namespace", ["", "a/*", "/lead", "trail/", "a b"])
def test_init_refuses_a_bad_namespace(tmp_path, namespace):
    with pytest.raises(SecureConfigError, match="namespace"):
        SecureInitConfig(tmp_path, namespace=namespace)


@pytest.mark.parametrize("endpoint", ["tcp/127.0.0.1:7447", "tls/127.0.0.1", "tls/:7447", "127.0.0.1:7447"])
def test_init_refuses_non_tls_router_endpoint(tmp_path, endpoint):
    with pytest.raises(SecureConfigError, match="tls/HOST:PORT"):
        SecureInitConfig(tmp_path, router_endpoint=endpoint)


def test_acl_is_default_deny_and_keyed_on_certificate_and_username():
    acl = build_acl("site-a")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert all(rule["permission"] == "allow" for rule in acl["rules"])
    subjects = {s["id"]: s for s in acl["subjects"]}
    for role in CLIENT_ROLES:  # certificate CN and username must both match
        assert subjects[role] == {"id": role, "cert_common_names": [role], "usernames": [role]}
    assert subjects["router"] == {"id": "router", "cert_common_names": ["router"]}
    worker_rules = next(p["rules"] for p in acl["policies"] if p["subjects"] == ["worker"])
    rules = {r["id"]: r for r in acl["rules"]}
    sent_by_worker = {m for rid in worker_rules for m in rules[rid]["messages"]
                      if rules[rid]["flows"] == ["ingress"]}
    assert sent_by_worker == {"query", "liveliness_token"}


# ---------------------------------------------------------------- the start-up check

def test_validate_accepts_the_written_profile(tmp_path):
    secure = init_secure(SecureInitConfig(tmp_path / "p"))
    files = validate_secure_config(secure.configs["router"])
    assert sorted(p.name for p in files) == ["ca.pem", "router-key.pem", "router.pem", "users.txt"]  # each once


@pytest.mark.parametrize("breakage, message", [
    ("missing", "is missing"),
    ("directory", "is unreadable"),
    ("not_pem", "is not a PEM file"),
])
def test_validate_refuses_missing_or_unreadable_files(tmp_path, breakage, message):
    secure = init_secure(SecureInitConfig(tmp_path / "p"))
    victim = tmp_path / "p" / "worker-key.pem"
    victim.unlink()
    if breakage == "directory":
        victim.mkdir()
    elif breakage == "not_pem":
        victim.write_text("hello\n")
    with pytest.raises(SecureConfigError, match=message) as info:
        validate_secure_config(secure.configs["worker"])
    text = str(info.value)
    assert "\n" not in text and "connect_private_key" in text and str(victim) in text


def test_check_lists_the_files_a_sound_profile_names_in_text_and_json(tmp_path, capsys):
    secure = init_secure(SecureInitConfig(tmp_path / "p", router_endpoint=f"tls/127.0.0.1:{free_port()}"))
    config = secure.configs["worker"]
    assert main(["secure", "check", str(config), "--json"]) == 0
    body = json.loads(capsys.readouterr().out)
    assert body["config"] == str(config) and body["files"] == [str(p) for p in validate_secure_config(config)]
    assert body["files"] and all(Path(f).is_file() for f in body["files"])
    assert main(["secure", "check", str(config)]) == 0
    out = capsys.readouterr().out
    assert f"{len(body['files'])} referenced file(s) present and readable" in out and body["files"][0] in out


def test_router_and_check_refuse_a_broken_profile_with_exit_2(tmp_path, capfd):
    secure = init_secure(SecureInitConfig(tmp_path / "p", router_endpoint=f"tls/127.0.0.1:{free_port()}"))
    (tmp_path / "p" / "users.txt").unlink()
    # the real command, in its own process: exit status 2 and one line on stderr
    done = subprocess.run(activecollect("router", "--zenoh-config", str(secure.configs["router"])),
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "users.txt is missing" in lines[0], done.stderr
    assert main(["secure", "check", str(secure.configs["router"])]) == 2
    assert "users.txt is missing" in capfd.readouterr().err


# ---------------------------------------------------------------- authentication

def test_wrong_password_cannot_open_a_session(secure_router, sessions):
    sessions.append(open_role(secure_router, "worker"))  # positive control
    assert sessions[-1].info.routers_zid()

    def wrong(cfg):
        cfg["transport"]["auth"]["usrpwd"]["password"] += "x"
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", wrong))

    def other_role(cfg):  # a real user with someone else's password
        cfg["transport"]["auth"]["usrpwd"]["user"] = "operator"
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", other_role))

    def none(cfg):
        del cfg["transport"]["auth"]
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", none))


def test_unknown_or_missing_client_certificate_cannot_connect(secure_router, sessions, tmp_path):
    sessions.append(open_role(secure_router, "worker"))  # positive control
    foreign = init_secure(SecureInitConfig(tmp_path / "foreign"))

    def unknown_ca(cfg):  # CN "worker", right password, but signed by another CA
        tls = cfg["transport"]["link"]["tls"]
        tls["connect_certificate"] = str(foreign.directory / "worker.pem")
        tls["connect_private_key"] = str(foreign.directory / "worker-key.pem")
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", unknown_ca))

    def missing(cfg):
        tls = cfg["transport"]["link"]["tls"]
        del tls["connect_certificate"], tls["connect_private_key"]
        tls["enable_mtls"] = False
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", missing))


def test_no_plaintext_endpoint_listens(secure_router, sessions):
    endpoint = json5.loads(secure_router.configs["worker"].read_text())["connect"]["endpoints"][0]
    sessions.append(open_role(secure_router, "worker"))  # positive control over TLS

    def plaintext(cfg):
        cfg["connect"]["endpoints"] = [endpoint.replace("tls/", "tcp/")]
        cfg["transport"]["link"]["protocols"] = ["tcp"]
    with pytest.raises(zenoh.ZError):
        sessions.append(open_role(secure_router, "worker", plaintext))


# ---------------------------------------------------------------- access control

def _serve(session: zenoh.Session, key: str, answer: bytes, calls: list[str]) -> zenoh.Queryable:
    def handler(query: zenoh.Query) -> None:
        calls.append(str(query.key_expr))
        query.reply(query.key_expr, answer)
    return session.declare_queryable(key, handler)


def test_worker_cannot_call_admin_but_operator_can(secure_router, sessions):
    orch, worker, operator = (open_role(secure_router, r) for r in ("orchestrator", "worker", "operator"))
    sessions += [orch, worker, operator]
    calls: list[str] = []
    sessions.append(_serve(orch, KEYS.admin_all, b"admin", calls))
    key = KEYS.admin("queue.ls") if hasattr(KEYS, "admin") else f"{NS}/admin/queue/ls"
    wait_for(lambda: get_payloads(operator, key) == [b"admin"], 10, "the operator's admin reply")
    before = len(calls)
    assert get_payloads(worker, key, timeout=1.0) == []
    assert get_payloads(worker, f"{NS}/**", timeout=1.0) == []  # a wildcard does not reach it either
    assert stays_false(lambda: len(calls) > before), calls


def test_worker_cannot_impersonate_the_orchestrator(secure_router, sessions):
    orch, honest, impostor = (open_role(secure_router, r) for r in ("orchestrator", "worker", "worker"))
    sessions += [orch, honest, impostor]
    real_calls: list[str] = []
    fake_calls: list[str] = []
    sessions.append(_serve(impostor, KEYS.lease, b"fake lease", fake_calls))
    sessions.append(_serve(orch, KEYS.lease, b"real lease", real_calls))
    wait_for(lambda: get_payloads(honest, KEYS.lease) == [b"real lease"], 10, "the real lease reply")
    for _ in range(3):
        assert get_payloads(honest, KEYS.lease, timeout=1.0) == [b"real lease"]
    assert fake_calls == [] and len(real_calls) >= 4


def test_only_the_orchestrator_publishes_events(secure_router, sessions):
    orch, worker, operator = (open_role(secure_router, r) for r in ("orchestrator", "worker", "operator"))
    sessions += [orch, worker, operator]
    seen: list[bytes] = []
    sessions.append(operator.declare_subscriber(KEYS.events_all, lambda s: seen.append(s.payload.to_bytes())))
    key = f"{NS}/events/request/done"

    def orchestrator_event_arrives() -> bool:
        orch.put(key, b"from orchestrator")
        return b"from orchestrator" in seen
    wait_for(orchestrator_event_arrives, 10, "the orchestrator's event at the operator", interval=0.2)
    worker.put(key, b"from worker")
    worker.delete(key)
    assert stays_false(lambda: any(p != b"from orchestrator" for p in seen)), seen


def test_worker_presence_reaches_the_orchestrator_only_from_workers(secure_router, sessions):
    orch, worker, operator = (open_role(secure_router, r) for r in ("orchestrator", "worker", "operator"))
    sessions += [orch, worker, operator]
    alive: set[str] = set()

    def on_change(sample: zenoh.Sample) -> None:
        (alive.add if sample.kind == zenoh.SampleKind.PUT else alive.discard)(str(sample.key_expr))
    sessions.append(orch.liveliness().declare_subscriber(KEYS.workers_all, on_change, history=True))
    op_token = operator.liveliness().declare_token(f"{NS}/workers/not-a-worker")
    token = worker.liveliness().declare_token(f"{NS}/workers/w1")
    wait_for(lambda: f"{NS}/workers/w1" in alive, 10, "the worker's liveliness token")
    assert stays_false(lambda: f"{NS}/workers/not-a-worker" in alive)
    token.undeclare()
    wait_for(lambda: f"{NS}/workers/w1" not in alive, 10, "the worker's token to go")
    op_token.undeclare()


def test_two_sites_linked_by_their_routers_keep_the_rules(secure_router, sessions):
    """Site B's router (same profile) links to site A's; a worker at B reaches the orchestrator
    at A for leases, and still not the admin keys."""
    site_a = json5.loads(secure_router.configs["worker"].read_text())["connect"]["endpoints"][0]
    site_b = f"tls/127.0.0.1:{free_port()}"
    router_b = start_router(secure_router.configs["router"], listen=(site_b,), connect=(site_a,))
    try:
        orch, operator = open_role(secure_router, "orchestrator"), open_role(secure_router, "operator")

        def at_site_b(cfg):
            cfg["connect"]["endpoints"] = [site_b]
        worker = open_role(secure_router, "worker", at_site_b)
        sessions += [orch, operator, worker]
        admin_calls: list[str] = []
        sessions.append(_serve(orch, KEYS.lease, b"real lease", []))
        sessions.append(_serve(orch, KEYS.admin_all, b"admin", admin_calls))
        wait_for(lambda: get_payloads(worker, KEYS.lease, timeout=1.0) == [b"real lease"], 15,
                   "a lease reply from site A at a worker of site B")
        wait_for(lambda: get_payloads(operator, f"{NS}/admin/queue/ls") == [b"admin"], 10, "admin reply")
        before = len(admin_calls)
        assert get_payloads(worker, f"{NS}/admin/queue/ls", timeout=1.0) == []
        assert stays_false(lambda: len(admin_calls) > before), admin_calls
    finally:
        for entity in reversed(sessions):
            entity.close() if isinstance(entity, zenoh.Session) else entity.undeclare()
        sessions.clear()
        assert router_b.stop() == 0, router_b.output()


def test_whole_loop_through_the_secure_router(secure_router, tmp_path, capsys):
    """The real service (orchestrator role), the operator CLI (operator role) and a real worker
    process (worker role), only through the TLS router with the ACL on: queue add, lease,
    collect, upload, done, stored once."""
    service = Service(ServiceConfig(data_dir=tmp_path / "data", zenoh_config=secure_router.configs["orchestrator"],
                                    lease_s=30.0))
    service.start()
    worker = None
    operator = ["--zenoh-config", str(secure_router.configs["operator"]), "--json"]
    try:
        assert main(["queue", "add", "--shape", "box", "--steps", "8", "--seed", "1", *operator]) == 0
        request_id = json.loads(capsys.readouterr().out)["request"]["id"]
        worker = Proc([sys.executable, "-m", "workers.agent", "--zenoh-config", str(secure_router.configs["worker"]),
                       "--id", "secure-w1", "--once"])
        assert worker.popen.wait(120) == 0, worker.output()
        wait_for(lambda: service.queue.get(request_id).status == RequestStatus.DONE, 30,
                   "the request to be done through the router")
        assert main(["queue", "show", request_id, *operator]) == 0
        shown = json.loads(capsys.readouterr().out)["request"]
        assert shown["status"] == "done" and shown["worker_id"] == "secure-w1"
        rows = service.catalog.list()
        assert [r.episode_id for r in rows] == [shown["episode_id"]] and rows[0].request_id == request_id
        # the ACL denies a worker the admin keys: dropped unanswered, so the refusal says that is why
        assert main(["stats", "--zenoh-config", str(secure_router.configs["worker"]), "--timeout", "1"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "no orchestrator answered" in err, err
        assert "is the secure profile's worker config" in err and "every role but operator" in err, err
    finally:
        if worker is not None:
            worker.stop()
        service.stop()


def test_the_operator_sees_whether_the_orchestrator_serves_admin(secure_router, sessions):
    """`watch` says when no service answers any more by a querier's matching status: the secure profile's rules
    must let the operator see the orchestrator's admin queryable come and go."""
    orch, operator = (open_role(secure_router, r) for r in ("orchestrator", "operator"))
    sessions += [orch, operator]
    querier = operator.declare_querier(KEYS.admin("stats"))
    sessions.append(querier)
    queryable = _serve(orch, KEYS.admin_all, b"admin", [])
    wait_for(lambda: querier.matching_status.matching, 10, "the operator to see the admin queryable")
    queryable.undeclare()
    wait_for(lambda: not querier.matching_status.matching, 10, "the operator to see it go")
