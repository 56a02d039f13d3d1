"""Who may send what, on which key, in a secure profile: the router's access control that `secure init` writes.

A leaf of the wire contract (workers import it): the roles, the rules the router enforces, and what a role's
config is refused by them, said before a process starts instead of its messages being dropped unanswered.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import zenoh

from orchestrator.protocol import Keys
from orchestrator.transport import lookup_key

#: Roles that get a config, a certificate and a password. The router is the only listener.
CLIENT_ROLES: tuple[str, ...] = ("orchestrator", "worker", "operator")
ROLES: tuple[str, ...] = ("router", *CLIENT_ROLES)
#: Every message kind Zenoh's ACL filters.
ACL_MESSAGES: tuple[str, ...] = ("put", "delete", "declare_subscriber", "query", "reply",
                                 "declare_queryable", "liveliness_token",
                                 "declare_liveliness_subscriber", "liveliness_query")
DEFAULT_NAMESPACE = "activecollect"
#: The key of a client config's ``metadata`` (which Zenoh keeps as it is) where ``secure init`` records the
#: profile's namespace.
NAMESPACE_METADATA = "activecollect_namespace"


def _rule(rule_id: str, flows: list[str], messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    """An allow rule; its id starts with the role whose policy it belongs to."""
    return {"id": rule_id, "permission": "allow", "flows": flows, "messages": messages,
            "key_exprs": key_exprs}


def build_acl(namespace: str = DEFAULT_NAMESPACE) -> dict[str, Any]:
    """The router's ``access_control`` section: default deny, one policy per role.

    Flows are seen from the router: ``ingress`` is what a role sends, ``egress`` what the
    router forwards to it. A message crosses the router only when the sender's ingress
    rule and the receiver's egress rule both allow it.
    """
    keys = Keys(namespace)
    ns = keys.namespace
    worker_keys = [keys.lease, keys.renew, keys.upload, keys.fail, keys.release]
    service_keys = [f"{ns}/orch/**", keys.admin_all]
    rules: list[dict[str, Any]] = [
        # orchestrator: serves the queryables, replies, publishes events, watches workers
        _rule("orchestrator-serve", ["ingress"], ["declare_queryable", "reply"], service_keys),
        _rule("orchestrator-publish", ["ingress"], ["put", "delete"], [keys.events_all]),
        _rule("orchestrator-watch", ["ingress"], ["declare_liveliness_subscriber", "liveliness_query"],
              [f"{ns}/workers/**"]),
        _rule("orchestrator-receive", ["egress"], ["query"], service_keys),
        _rule("orchestrator-receive-workers", ["egress"], ["liveliness_token", "reply"],
              [f"{ns}/workers/**"]),
        _rule("orchestrator-see-subscribers", ["egress"], ["declare_subscriber"], [keys.events_all]),
        # worker: asks for work and reports presence, nothing else
        _rule("worker-ask", ["ingress"], ["query"], worker_keys),
        _rule("worker-presence", ["ingress"], ["liveliness_token"], [keys.workers_all]),
        _rule("worker-answers", ["egress"], ["reply", "declare_queryable"], worker_keys),
        # operator: admin queries and the event stream
        _rule("operator-ask", ["ingress"], ["query"], [keys.admin_all]),
        _rule("operator-watch", ["ingress"], ["declare_subscriber"], [keys.events_all]),
        _rule("operator-answers", ["egress"], ["reply", "declare_queryable"], [keys.admin_all]),
        _rule("operator-events", ["egress"], ["put", "delete"], [keys.events_all]),
        # router: another site's router (same profile) carries all of this namespace both ways;
        # each router enforces the rules above on its own clients
        _rule("router-link", ["ingress", "egress"], list(ACL_MESSAGES), [f"{ns}/**"]),
    ]
    # A router linked to another one is only authenticated by user/password on the side it
    # connects to; the side it connects from knows only the certificate. Hence CN only there.
    subjects: list[dict[str, Any]] = [{"id": "router", "cert_common_names": ["router"]}]
    subjects += [{"id": role, "cert_common_names": [role], "usernames": [role]} for role in CLIENT_ROLES]
    by_role: dict[str, list[str]] = {role: [] for role in ROLES}
    for rule in rules:
        by_role[rule["id"].split("-", 1)[0]].append(rule["id"])
    policies = [{"id": f"{role}-policy", "rules": ids, "subjects": [role]}
                for role, ids in by_role.items()]
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def roles_that_may_send(key_expr: str, namespace: str = DEFAULT_NAMESPACE, message: str = "query") -> tuple[str, ...]:
    """The client roles whose rules in ``build_acl(namespace)`` let them send ``message`` (a query, or
    "declare_queryable") on all of ``key_expr``: the router drops another role's there, unanswered."""
    wanted = zenoh.KeyExpr(key_expr)
    roles = {rule["id"].split("-", 1)[0] for rule in build_acl(namespace)["rules"]
             if "ingress" in rule["flows"] and message in rule["messages"]
             and any(zenoh.KeyExpr(k).includes(wanted) for k in rule["key_exprs"])}
    return tuple(role for role in CLIENT_ROLES if role in roles)


def client_role(config: dict[str, Any]) -> str | None:
    """The role a parsed client config of a secure profile logs in as: its usrpwd user, which ``client_config``
    writes as the role's name (the ACL matches it with the certificate's CN). None for any other config."""
    user = lookup_key(config, "transport/auth/usrpwd/user")
    if lookup_key(config, "transport/link/protocols") != ["tls"] or not isinstance(user, str):
        return None
    return user if user in CLIENT_ROLES else None


def denied_by_acl(config: dict[str, Any], config_path: Path, key_expr: str, namespace: str, what: str,
                   message: str = "query") -> str | None:
    """Why ``message``s (queries, or "declare_queryable") on ``key_expr`` with this parsed config will go unanswered,
    when it is the config of a secure profile's role that the profile's ACL does not let send them there (``what``:
    "admin queries", say), or the profile's of another namespace (its ACL lets none of this one's keys through);
    else None."""
    recorded = lookup_key(config, f"metadata/{NAMESPACE_METADATA}")
    if isinstance(recorded, str) and recorded != namespace:  # (profiles from before it was recorded: not known)
        return (f"{config_path} is a secure profile of the namespace {recorded!r}, whose router's ACL drops every "
                f"key of {namespace!r}: give --namespace {recorded} (or a profile made with secure init "
                f"--namespace {namespace})")
    role, allowed = client_role(config), roles_that_may_send(key_expr, namespace, message)
    if role is None or not allowed or role in allowed:
        return None
    other = config_path.with_name(f"{allowed[0]}.json5")
    use = f"give --zenoh-config {other}" if other.is_file() else f"use the profile's {allowed[0]}.json5"
    unanswered = " unanswered" if message == "query" else ""
    return (f"{config_path} is the secure profile's {role} config, and the router's ACL drops {what} from every "
            f"role but {' and '.join(allowed)}{unanswered} ({use})")
