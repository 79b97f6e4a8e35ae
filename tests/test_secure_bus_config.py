"""Unit tests of the secured bus's pieces: certificates, TLS settings, the generated access control."""

from __future__ import annotations

import base64
import stat

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from agos.deploy.ops.certs import main as certs_main
from agos.deploy.ops.certs import make_certs, zenohd_config
from agos.runtime import keys
from agos.runtime.access_control import IDENTITIES, access_control
from agos.runtime.bus import session_config
from agos.runtime.settings import ConfigError, ZenohSettings, load_config
from agos.runtime.tls import tls_section


def _allowed(identity: str, message: str, flow: str, key: str) -> bool:
    """Whether the generated rules let ``identity`` send (ingress) or receive (egress) ``message`` on ``key``."""
    acl = access_control()
    policy = next((p for p in acl["policies"] if identity in p["subjects"]), None)
    if policy is None:
        return False
    rules = [r for r in acl["rules"] if r["id"] in policy["rules"]]
    return any(message in r["messages"] and flow in r["flows"]
               and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"]) for r in rules)


def test_who_may_publish_what() -> None:
    act_uav, act_ugv = keys.act("r", "e", "uav"), keys.act("r", "e", "ugv")
    result, ack = keys.result("r", "e"), keys.result_ack("r", "e")
    assert _allowed("agent-uav", "put", "ingress", act_uav)
    assert not _allowed("agent-uav", "put", "ingress", act_ugv)
    assert not _allowed("agent-uav", "put", "ingress", result)
    assert not _allowed("agent-ugv", "put", "ingress", act_uav)
    # A router relays everything (tests/test_router_mesh.py); among the processes' identities:
    clients = [i for i in IDENTITIES if i != "router"]
    assert [i for i in clients if _allowed(i, "put", "ingress", ack)] == ["evaluator"]
    assert sorted(i for i in clients if _allowed(i, "put", "ingress", result)) == ["orchestrator", "world"]
    for key in (keys.obs("r", "e", "uav"), keys.events("r", "e"), keys.coord_truth("r", "e"),
                keys.message("r", "e", "uav", "ugv"), keys.viz_frame("r", "e", "uav")):
        assert _allowed("world", "put", "ingress", key)
        assert not _allowed("agent-uav", "put", "ingress", key)
    # Observers hear the visualisation stream and nothing else.
    assert _allowed("observer", "put", "egress", keys.viz_events("r", "e"))
    assert not _allowed("observer", "put", "egress", act_uav)
    assert not _allowed("observer", "declare_subscriber", "ingress", "agos/**")
    assert not _allowed("observer", "put", "ingress", keys.viz_events("r", "e"))
    # Each agent hears only its own role's observations.
    assert _allowed("agent-ugv", "put", "egress", keys.obs("r", "e", "ugv"))
    assert not _allowed("agent-ugv", "put", "egress", keys.obs("r", "e", "uav"))
    # Every identity may ask whether processes are alive (agos health).
    assert all(_allowed(i, "liveliness_query", "ingress", keys.live("r", "world", "w1")) for i in IDENTITIES)
    assert not _allowed("stranger", "put", "ingress", act_uav)


def test_access_control_is_a_valid_zenoh_router_config(tmp_path) -> None:
    make_certs(tmp_path)
    z = ZenohSettings(listen="tls/127.0.0.1:7447", ca_file=tmp_path / "ca.pem", cert_file=tmp_path / "router.pem",
                      key_file=tmp_path / "router.key")
    session_config(z, mode="router", access_control=access_control())  # zenoh refuses unknown or bad fields
    assert zenohd_config()["access_control"] == access_control()


def test_certificates_name_their_identity_and_keys_are_private(tmp_path) -> None:
    files = make_certs(tmp_path / "c", router_hosts=["core.lan", "10.0.0.5"])
    ca = x509.load_pem_x509_certificate((tmp_path / "c" / "ca.pem").read_bytes())
    for identity in IDENTITIES:
        cert = x509.load_pem_x509_certificate((tmp_path / "c" / f"{identity}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == identity
        assert cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
    router = x509.load_pem_x509_certificate((tmp_path / "c" / "router.pem").read_bytes())
    names = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "core.lan" in names.get_values_for_type(x509.DNSName)
    assert [str(a) for a in names.get_values_for_type(x509.IPAddress)] == ["10.0.0.5"]
    for path in files:
        if path.suffix == ".key":
            assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert certs_main(tmp_path / "c", router_hosts=None, days=1, force=False) == 2  # never replaces a CA silently


def test_tls_settings_name_what_is_missing_and_take_pem_from_the_environment(tmp_path) -> None:
    make_certs(tmp_path)
    z = ZenohSettings(connect="tls/127.0.0.1:7447", ca_file=tmp_path / "ca.pem")
    with pytest.raises(ConfigError, match=r"zenoh.cert_file: .*AGOS_ZENOH__CERT_FILE"):
        tls_section(z, listening=False)
    with pytest.raises(ConfigError, match=r"zenoh.ca_file: .*nowhere.pem: file not found"):
        tls_section(z.model_copy(update={"ca_file": tmp_path / "nowhere.pem"}), listening=False)
    key_pem = (tmp_path / "world.key").read_text()
    cfg = load_config(environ={"AGOS_ZENOH__CONNECT": "tls/127.0.0.1:7447",
                               "AGOS_ZENOH__CA_FILE": str(tmp_path / "ca.pem"),
                               "AGOS_ZENOH__CERT_FILE": str(tmp_path / "world.pem"),
                               "AGOS_ZENOH__KEY_PEM": key_pem})
    assert key_pem not in repr(cfg) and key_pem not in str(cfg.zenoh)  # a secret never prints
    section = tls_section(cfg.zenoh, listening=False)
    assert base64.b64decode(section["connect_private_key_base64"]).decode() == key_pem
    assert section["connect_certificate"] == str(tmp_path / "world.pem")
    assert section["enable_mtls"] is True
    assert session_config(ZenohSettings()) is not None  # plain TCP needs no credentials
