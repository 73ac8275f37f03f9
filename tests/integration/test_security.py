"""Who may do what (hdmap/ops/security.py), over real TLS connections to a real router process.

One secured stack (mTLS, ACL) with the real ingest and publisher processes serves the
module; the user/password variant gets its own router. Denials are silent in Zenoh (a
denied put returns, a denied subscription is declared), so every "cannot" is shown by
what the other side does or does not receive, next to a control that does receive.
A session serves its own queries and subscriptions locally, without the router: each
actor below has its own session.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh

from fleetsim.synthetic import make_observations
from hdmap.ops.security import (
    SERVICE_IDENTITIES,
    SecureDeployment,
    acl,
    create_ca,
    generate,
    issue_certificate,
)
from hdmap.ops.stack import Stack, free_port
from hdmap.ops.status import collect
from hdmap.runtime.bus import BusConfig, open_session, query
from schemas import ErrorReply, MapSnapshot, ObservationBatch, UploadAck, keys
from tests.support import wait_until

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
TILE = "1202032333101011"
VEHICLES = ["veh-1", "veh-2"]
QUIET_S = 1.0
"""Bounded wait after which "nothing was received" is asserted."""


@pytest.fixture(scope="module")
def mtls(tmp_path_factory) -> Iterator[tuple[Stack, SecureDeployment]]:
    root = tmp_path_factory.mktemp("mtls")
    dep = generate(root / "secure", VEHICLES, f"tls/127.0.0.1:{free_port()}", "mtls")
    stack = Stack(root / "stack", listen=dep.endpoint, security=dep)
    try:
        stack.start_router()
        stack.start_service("ingest")
        stack.start_service("publisher")
        stack.wait_ready(["ingest-all", "publisher-all"], 60)  # the operator identity works
        yield stack, dep
    finally:
        stack.stop_all()


def batch(vehicle: str, batch_id: int, first_id: int = 1) -> bytes:
    obs = make_observations(5, seed=batch_id)
    obs.obs_id[:] = range(first_id, first_id + 5)
    return ObservationBatch(vehicle, 1, batch_id, time.time(), obs).to_bytes()


def sessions(es: ExitStack, dep: SecureDeployment, *identities: str) -> list[zenoh.Session]:
    return [es.enter_context(open_session(dep.bus(i))) for i in identities]


def collector(es: ExitStack, s: zenoh.Session, key: str) -> list[tuple[str, bytes]]:
    got: list[tuple[str, bytes]] = []
    sub = s.declare_subscriber(key, lambda m: got.append((str(m.kind), m.payload.to_bytes())))
    es.callback(sub.undeclare)
    return got


def until_received(send: Callable[[], object], got: list, timeout: float = 10.0) -> bool:
    """Send (again) until ``got`` is not empty: subscriptions take a moment to propagate."""
    return wait_until(lambda: bool(send()) or bool(got), timeout, 0.1)


def ingest_counter(op: zenoh.Session, name: str) -> float:
    return {st.service: st for st in collect(op)}["ingest"].counters.get(name, 0)


def test_vehicle_uploads_as_itself_and_reads_the_map(mtls):
    _stack, dep = mtls
    with ExitStack() as es:
        veh, pub = sessions(es, dep, "veh-1", "publisher")
        replies = query(veh, keys.upload("veh-1"), batch("veh-1", 1), timeout=10.0)
        assert len(replies) == 1 and replies[0][1] is not None
        ack = UploadAck.from_bytes(replies[0][1])
        assert ack.error is None and sorted(ack.accepted.tolist()) == [1, 2, 3, 4, 5]

        snaps = query(veh, keys.map_snapshot_for("veh-1", TILE), timeout=10.0)
        assert len(snaps) == 1 and snaps[0][1] is not None  # from the publisher process
        snap = MapSnapshot.from_bytes(snaps[0][1])
        assert snap.tile == TILE and len(snap.landmarks) == 0
        assert snaps[0][0] == keys.map_snapshot_for("veh-1", TILE)

        got = collector(es, veh, keys.map_delta(TILE))
        assert until_received(lambda: pub.put(keys.map_delta(TILE), b"delta"), got)
        assert got[0] == ("SampleKind.PUT", b"delta")


def test_vehicle_cannot_publish_a_map_delta(mtls):
    _stack, dep = mtls
    with ExitStack() as es:
        veh, pub, listener = sessions(es, dep, "veh-1", "publisher", "ingest")
        got = collector(es, listener, keys.map_delta(keys.ANY))
        got_obs = collector(es, listener, keys.obs(keys.ANY))
        # Control: a service's delta reaches the listening service.
        assert until_received(lambda: pub.put(keys.map_delta(TILE), b"control"), got)
        assert veh.put(keys.map_delta(TILE), b"forged") is None  # no error: dropped silently
        veh.delete(keys.map_delta(TILE))
        veh.put(keys.obs(TILE), b"forged")
        fence = keys.map_snapshot_for("veh-1", TILE)
        assert len(query(veh, fence, timeout=10.0)) == 1  # a fence on the link
        time.sleep(QUIET_S)
        assert all(payload == b"control" for _kind, payload in got)
        assert {kind for kind, _p in got} == {"SampleKind.PUT"}
        assert got_obs == []


def test_vehicle_cannot_upload_under_another_id(mtls):
    _stack, dep = mtls
    with ExitStack() as es:
        veh1, veh2, op = sessions(es, dep, "veh-1", "veh-2", "operator")
        before = ingest_counter(op, "uploads")
        for selector in (keys.upload("veh-2"), keys.upload(keys.ANY), f"{keys.ROOT}/upload/**"):
            t0 = time.monotonic()
            assert query(veh1, selector, batch("veh-2", 2, 100), timeout=5.0) == []
            assert time.monotonic() - t0 < 2.0  # denied at the router: answered at once, empty
        assert ingest_counter(op, "uploads") == before  # ingest never saw them
        # Control: the same batch from veh-2 itself is accepted.
        ack = UploadAck.from_bytes(query(veh2, keys.upload("veh-2"), batch("veh-2", 2, 100))[0][1])
        assert sorted(ack.accepted.tolist()) == [100, 101, 102, 103, 104]
        assert ingest_counter(op, "uploads") == before + 1


def publisher_rejected(op: zenoh.Session) -> dict[str, int]:
    return dict({st.service: st for st in collect(op)}["publisher"].rejected)


def test_vehicle_asks_for_snapshots_only_under_its_own_id(mtls):
    _stack, dep = mtls
    with ExitStack() as es:
        veh1, veh2, op = sessions(es, dep, "veh-1", "veh-2", "operator")
        before = publisher_rejected(op)
        denied = (
            keys.map_snapshot_for("veh-2", TILE),  # another vehicle's budget
            keys.map_snapshot(TILE),  # anonymous: the shared budget
            keys.map_snapshot_for(keys.ANY, TILE),
            f"{keys.ROOT}/map/**",
        )
        for selector in denied:
            t0 = time.monotonic()
            assert query(veh1, selector, timeout=5.0) == [], selector
            assert time.monotonic() - t0 < 2.0  # denied at the router: answered at once, empty
        # Control: its own key is answered (the operator may use the anonymous one).
        (mine,) = query(veh1, keys.map_snapshot_for("veh-1", TILE), timeout=10.0)
        assert MapSnapshot.from_bytes(mine[1]).tile == TILE
        assert len(query(op, keys.map_snapshot(TILE), timeout=10.0)) == 1
        # Over its budget (200 at once by default), the refusal reaches the vehicle too
        # (veh-2: the module's other tests use veh-1's budget).
        refusal = None
        for _ in range(400):
            (reply,) = query(veh2, keys.map_snapshot_for("veh-2", TILE), timeout=10.0)
            if reply[2] is not None:
                refusal = ErrorReply.from_bytes(reply[2])
                break
        assert refusal is not None and (refusal.code, refusal.field) == ("rate", "snapshot.client")
        assert refusal.retry_after_s > 0 and "'veh-2'" in refusal.reason
        after = publisher_rejected(op)
        assert after.get("snapshot.client", 0) == before.get("snapshot.client", 0) + 1
        assert after.get("snapshot.tile", 0) == before.get("snapshot.tile", 0)  # none got there


def test_vehicle_cannot_subscribe_to_internal_keys(mtls):
    _stack, dep = mtls
    internal = [keys.obs(keys.ANY), keys.update(keys.ANY), keys.assoc(keys.ANY)]
    with ExitStack() as es:
        veh, svc = sessions(es, dep, "veh-1", "operator")
        denied = {k: collector(es, veh, k) for k in internal}
        control = collector(es, veh, keys.map_delta(TILE))

        def publish_all() -> None:
            for k in internal:  # garbage for a live consumer: rejected, never applied
                svc.put(k.replace(keys.ANY, TILE), b"internal")
            svc.put(keys.map_delta(TILE), b"allowed")

        assert until_received(publish_all, control)  # the vehicle's session does receive
        publish_all()
        time.sleep(QUIET_S)
        assert {k: v for k, v in denied.items() if v} == {}
        # Nor can it see the services' liveliness tokens, stats or logs.
        assert [r for r in veh.liveliness().get(f"{keys.ROOT}/alive/**", timeout=2.0)] == []
        assert query(veh, f"{keys.ROOT}/stats/**", timeout=2.0) == []
        assert query(veh, f"{keys.ROOT}/log/obs/*/*", timeout=2.0) == []


def test_vehicle_cannot_impersonate_a_service(mtls):
    _stack, dep = mtls
    with ExitStack() as es:
        veh, op = sessions(es, dep, "veh-1", "operator")

        def forged(q: zenoh.Query) -> None:
            q.reply(q.key_expr, b"forged")

        qbl = veh.declare_queryable(keys.map_snapshot(keys.ANY), forged)
        es.callback(qbl.undeclare)
        token = veh.liveliness().declare_token(keys.alive("publisher", "all", "forged"))
        es.callback(token.undeclare)
        time.sleep(QUIET_S)
        replies = query(op, keys.map_snapshot(TILE), timeout=5.0)
        assert [MapSnapshot.from_bytes(r[1]).tile for r in replies if r[1]] == [TILE]
        alive = [
            str(r.ok.key_expr)
            for r in op.liveliness().get(f"{keys.ROOT}/alive/**", timeout=2.0)
            if r.ok
        ]
        assert len(alive) == 2 and not any(a.endswith("/forged") for a in alive)


def tls_client(endpoint: str, tls: dict, user: tuple[str, str] | None = None) -> BusConfig:
    extra = [("transport/link/tls", json.dumps(tls))]
    if user is not None:
        usrpwd = {"user": user[0], "password": user[1]}
        extra.append(("transport/auth/usrpwd", json.dumps(usrpwd)))
    return BusConfig(connect=(endpoint,), extra=tuple(extra))


def cannot_connect(cfg: BusConfig) -> None:
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError, match="Unable to connect"), open_session(cfg):
        pass
    assert time.monotonic() - t0 < 5.0


def test_mtls_client_without_a_valid_certificate_cannot_connect(mtls, tmp_path):
    _stack, dep = mtls
    ca = str(dep.pki / "ca.pem")
    cannot_connect(BusConfig(connect=(dep.endpoint.replace("tls/", "tcp/"),)))  # plain TCP
    cannot_connect(tls_client(dep.endpoint, {"root_ca_certificate": ca}))  # no certificate
    other_ca, other_key = create_ca(tmp_path / "other")
    cert, key = issue_certificate(other_ca, other_key, "veh-1", tmp_path / "other")
    mtls_conf = {"enable_mtls": True, "connect_certificate": str(cert)}
    cannot_connect(  # right name, wrong CA
        tls_client(
            dep.endpoint, {"root_ca_certificate": ca, **mtls_conf, "connect_private_key": str(key)}
        )
    )
    # A certificate of our CA whose name is not in the ACL (a revoked vehicle) connects
    # but may do nothing.
    cert, key = issue_certificate(dep.pki / "ca.pem", dep.pki / "ca.key", "veh-9", tmp_path)
    mtls_conf = {"enable_mtls": True, "connect_certificate": str(cert)}
    with ExitStack() as es:
        (pub,) = sessions(es, dep, "publisher")
        unknown = es.enter_context(
            open_session(
                tls_client(
                    dep.endpoint,
                    {"root_ca_certificate": ca, **mtls_conf, "connect_private_key": str(key)},
                )
            )
        )
        assert query(unknown, keys.upload("veh-9"), batch("veh-9", 3), timeout=5.0) == []
        assert query(unknown, keys.map_snapshot(TILE), timeout=5.0) == []
        got = collector(es, unknown, keys.map_delta(TILE))
        pub.put(keys.map_delta(TILE), b"delta")
        time.sleep(QUIET_S)
        assert got == []


def read_json5(path) -> dict:
    return json.loads("".join(ln for ln in open(path) if not ln.startswith("//")))


def test_usrpwd_authenticates_and_scopes_by_user_name(tmp_path):
    dep = generate(tmp_path / "secure", VEHICLES, f"tls/127.0.0.1:{free_port()}", "usrpwd")
    assert not any(dep.pki.glob("veh-*.pem"))  # no client certificates in this mode
    ca = {"root_ca_certificate": str(dep.pki / "ca.pem")}
    password = read_json5(dep.vehicle_config("veh-1"))["transport"]["auth"]["usrpwd"]["password"]
    st = Stack(tmp_path / "stack", listen=dep.endpoint, security=dep)
    try:
        st.start_router()
        cannot_connect(tls_client(dep.endpoint, ca))  # no credentials
        cannot_connect(tls_client(dep.endpoint, ca, ("veh-1", password + "x")))  # wrong password
        cannot_connect(tls_client(dep.endpoint, ca, ("veh-2", password)))  # another's password
        cannot_connect(tls_client(dep.endpoint, ca, ("nobody", password)))  # unknown user
        with ExitStack() as es:
            svc, veh = sessions(es, dep, "ingest", "veh-1")

            def ack(q: zenoh.Query) -> None:
                q.reply(q.key_expr, b"ack")

            qbl = svc.declare_queryable(keys.upload(keys.ANY), ack)
            es.callback(qbl.undeclare)
            assert wait_until(lambda: bool(query(veh, keys.upload("veh-1"), timeout=2.0)), 10)
            assert query(veh, keys.upload("veh-2"), timeout=2.0) == []
            got = collector(es, svc, keys.map_delta(keys.ANY))
            veh.put(keys.map_delta(TILE), b"forged")
            time.sleep(QUIET_S)
            assert got == []
    finally:
        st.stop_all()


def test_acl_has_no_wildcard_subject_and_one_upload_rule_per_vehicle():
    a = acl(["ingest", "operator"], ["v1", "v2", "v3"], "usrpwd")
    assert a["default_permission"] == "deny"
    assert all(s["usernames"] for s in a["subjects"])  # a subject without names matches anyone
    own = [r for r in a["rules"] if r["id"].startswith("own-")]
    assert [r["key_exprs"] for r in own] == [
        [keys.upload(v), keys.map_snapshot_for(v, keys.ANY)] for v in ("v1", "v2", "v3")
    ]
    assert all(r["flows"] == ["ingress"] and r["messages"] == ["query"] for r in own)
    vehicle_in = [
        r for r in a["rules"] if r["id"].startswith("vehicle-") and "ingress" in r["flows"]
    ]
    assert {m for r in vehicle_in for m in r["messages"]} == {"declare_subscriber"}
    # no shared right to query anything: snapshots only under the vehicle's own id
    shared = [r for r in a["rules"] if r["id"].startswith("vehicle-")]
    assert not [r for r in shared if "query" in r["messages"]]
    assert acl([], [], "mtls")["subjects"] == []
    with pytest.raises(ValueError):
        acl(["ingest"], ["veh/1"])
    # deploy/secure/router.json5 shows what the generator writes.
    example = zenoh.Config.from_file(str(ROOT / "deploy" / "secure" / "router.json5"))
    shown = json.loads(example.get_json("access_control"))
    shown["subjects"] = [{k: v for k, v in s.items() if v is not None} for s in shown["subjects"]]
    assert shown == acl(SERVICE_IDENTITIES, ["veh-1", "veh-2"], "mtls")
