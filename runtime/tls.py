"""Mutual TLS for zenoh links: a process's credentials (settings) -> zenoh's ``transport/link/tls``.

Every process on a secured bus holds a certificate signed by the run's CA (``agos certs``); the
certificate's common name is its identity, which the router's access control maps to what it may
say and hear (runtime/access_control.py). Clients present theirs when they connect (``connect_*``),
the router when it accepts (``listen_*``), and each side checks the other against the CA.

Credentials are paths (``*_file``) or PEM text from the environment (``*_pem``, passed to zenoh as
base64 so nothing is written to disk). Neither is ever logged: errors name the setting, not its value.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

from pydantic import SecretStr

from agos.runtime.settings import ConfigError, ZenohSettings

_MAKE_THEM = "make them with `agos certs --out DIR` (docs/DEPLOY.md)"


def _credential(z: ZenohSettings, name: str, what: str, endpoint: str) -> tuple[str, str]:
    """(``"path"`` or ``"base64"``, value) of one credential, or a ConfigError naming both settings."""
    path: Path | None = getattr(z, f"{name}_file")
    pem = getattr(z, f"{name}_pem")
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"config error: zenoh.{name}_file: {path}: file not found ({what}); {_MAKE_THEM}")
        return "path", str(path)
    if pem is not None:
        text = pem.get_secret_value() if isinstance(pem, SecretStr) else pem
        if "-----BEGIN" not in text:
            raise ConfigError(f"config error: zenoh.{name}_pem: not PEM text ({what})")
        return "base64", base64.b64encode(text.encode()).decode()
    raise ConfigError(f"config error: zenoh.{name}_file: endpoint {endpoint} uses TLS and needs {what}: set "
                      f"AGOS_ZENOH__{name.upper()}_FILE (or AGOS_ZENOH__{name.upper()}_PEM); {_MAKE_THEM}")


def tls_section(z: ZenohSettings, *, listening: bool) -> dict[str, Any]:
    """zenoh's ``transport/link/tls`` for this process: mutual TLS, the peer checked against the CA.
    A router (``listening``) with peers presents the same certificate on the links it opens to them
    (``zenoh.peers``: a router mesh), and checks their names as clients do."""
    sides = ["listen", *(["connect"] if z.peers else [])] if listening else ["connect"]
    endpoint = z.listen if listening else z.connect
    section: dict[str, Any] = {"enable_mtls": True, "verify_name_on_connect": z.verify_name}
    names = [("ca", "root_ca_certificate", "the CA certificate")]
    for side in sides:
        names += [("cert", f"{side}_certificate", "this process's certificate"),
                  ("key", f"{side}_private_key", "this process's private key")]
    for name, zenoh_name, what in names:
        kind, value = _credential(z, name, what, endpoint)
        section[zenoh_name if kind == "path" else f"{zenoh_name}_base64"] = value
    return section
