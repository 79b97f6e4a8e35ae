"""``agos certs --out DIR``: a CA and one certificate per identity of a secured bus.

Writes ``DIR/ca.pem`` and ``DIR/ca.key`` (the CA: keep ``ca.key`` off every host but the one that
signs), and for each identity of runtime/access_control.py ``DIR/<identity>.pem`` and
``DIR/<identity>.key``. A certificate's common name is its identity: it decides what the router
lets that process say and hear. Each host gets ``ca.pem`` plus the pairs of the processes it runs.

The router's certificate also names the hosts clients reach it by (``--router-host``, default
localhost and 127.0.0.1), because clients check the name (``zenoh.verify_name``).
Keys are ECDSA P-256, certificates valid ``--days`` (365); private keys are written 0600.

``zenohd.json5`` is a configuration for the official router image (``eclipse/zenoh``) with the same
TLS and access control, for the compose router switch (docs/DEPLOY.md).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import shutil
import tempfile
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from agos.runtime.access_control import IDENTITIES, access_control
from agos.runtime.settings import ZenohSettings

CA_NAME = "agos-ca"
CONTAINER_CERTS = "/certs"
"""Where the compose files mount a host's certificates inside containers (zenohd.json5 names it)."""


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "agos"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)  # also when the file existed with wider permissions


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _alt_names(hosts: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def make_certs(out: Path, *, router_hosts: list[str] | None = None, days: int = 365,
               identities: list[str] | None = None) -> list[Path]:
    """Write the CA and the identities' certificates under ``out``; return the files written."""
    router_hosts = router_hosts or ["localhost", "127.0.0.1"]
    identities = identities or list(IDENTITIES)
    unknown = [i for i in identities if i not in IDENTITIES]
    if unknown:
        raise ValueError(f"unknown identity {unknown[0]!r}; known: {', '.join(IDENTITIES)}")
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    now = datetime.datetime.now(datetime.UTC)
    not_before, not_after = now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (x509.CertificateBuilder().subject_name(_name(CA_NAME)).issuer_name(_name(CA_NAME))
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(not_before).not_valid_after(not_after)
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                       content_commitment=False, key_encipherment=False, data_encipherment=False,
                                       key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
          .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
          .sign(ca_key, hashes.SHA256()))
    written = [out / "ca.pem", out / "ca.key"]
    _write_cert(written[0], ca)
    _write_key(written[1], ca_key)
    for identity in identities:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (x509.CertificateBuilder().subject_name(_name(identity)).issuer_name(ca.subject)
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(not_before).not_valid_after(not_after)
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                                  critical=False)
                   .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False))
        # rustls wants a subject alternative name on every end-entity certificate; the router's names
        # the hosts clients dial, the others their identity.
        alt = _alt_names(router_hosts) if identity == "router" else [x509.DNSName(identity)]
        cert = builder.add_extension(x509.SubjectAlternativeName(alt), critical=False).sign(ca_key, hashes.SHA256())
        _write_cert(out / f"{identity}.pem", cert)
        _write_key(out / f"{identity}.key", key)
        written += [out / f"{identity}.pem", out / f"{identity}.key"]
    zenohd = out / "zenohd.json5"
    zenohd.write_text(json.dumps(zenohd_config(), indent=2) + "\n")
    written.append(zenohd)
    return written


def zenohd_config(listen: str = "tls/0.0.0.0:7447", certs_dir: str = CONTAINER_CERTS) -> dict[str, object]:
    """A zenohd configuration with agos's TLS and access control (for the ``eclipse/zenoh`` image)."""
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": {
            "root_ca_certificate": f"{certs_dir}/ca.pem",
            "listen_certificate": f"{certs_dir}/router.pem",
            "listen_private_key": f"{certs_dir}/router.key",
            # Presented to other routers when it connects to them (a router mesh: add connect/endpoints).
            "connect_certificate": f"{certs_dir}/router.pem",
            "connect_private_key": f"{certs_dir}/router.key",
            "enable_mtls": True,
        }}},
        "access_control": access_control(),
    }


def main(out: Path, *, router_hosts: list[str] | None, days: int, force: bool) -> int:
    from rich.console import Console

    console = Console()
    if (out / "ca.key").exists() and not force:
        console.print(f"[red]{out / 'ca.key'} exists: a second CA would not match the certificates already handed "
                      "out; pass --force to replace them all, or choose another --out")
        return 2
    files = make_certs(out, router_hosts=router_hosts, days=days)
    console.print(f"wrote {len(files)} files to {out}: ca.pem, ca.key (keep it here), and a certificate and key for "
                  f"each of {', '.join(IDENTITIES)}; zenohd.json5 for the eclipse/zenoh router image", highlight=False)
    return 0


def credential_env(certs: Path, identity: str) -> dict[str, str]:
    """The ``AGOS_ZENOH__*`` variables naming ``identity``'s files in a directory made by :func:`make_certs`."""
    return {"AGOS_ZENOH__CA_FILE": str(certs / "ca.pem"), "AGOS_ZENOH__CERT_FILE": str(certs / f"{identity}.pem"),
            "AGOS_ZENOH__KEY_FILE": str(certs / f"{identity}.key")}


class RunCredentials:
    """A throwaway CA and certificates for one local secured run (``agos eval/demo --secure``): made in
    a private temporary directory, handed to each child as the ``[zenoh]`` settings naming its files
    (which reach it as environment variables, never on a command line: deploy/run/children.py),
    removed when the run ends."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="agos-certs-"))
        make_certs(self.dir)

    def files(self, identity: str) -> dict[str, Path]:
        """``identity``'s credentials as ``[zenoh]`` settings: ``ca_file``, ``cert_file``, ``key_file``."""
        return {"ca_file": self.dir / "ca.pem", "cert_file": self.dir / f"{identity}.pem",
                "key_file": self.dir / f"{identity}.key"}

    def settings(self, z: ZenohSettings, identity: str, endpoint: str) -> ZenohSettings:
        """``z`` connecting to ``endpoint`` as ``identity`` (for this process's own session)."""
        return z.model_copy(update={"connect": endpoint, **self.files(identity)})

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
