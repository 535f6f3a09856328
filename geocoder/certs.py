"""TLS certificates for a geocoder cluster: one CA, a key and certificate per role.

Files (PEM), the same names as ``deploy/make-certs.sh`` writes: ``ca.pem`` / ``ca-key.pem``,
and ``scheduler.pem`` / ``scheduler-key.pem``, ``worker.pem`` / ``worker-key.pem``,
``client.pem`` / ``client-key.pem``. Dask verifies both ends of every connection against
the CA, so a client without a certificate signed by it is refused.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from typing import Iterable

ROLES = ("scheduler", "worker", "client")
DEFAULT_NAMES = ("localhost", "127.0.0.1", "scheduler", "worker", "notebook")


def _san(names: Iterable[str]):
    from cryptography import x509

    out = []
    for n in names:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            out.append(x509.DNSName(n))
    return x509.SubjectAlternativeName(out)


def make_certificates(directory: str | os.PathLike, *, names: Iterable[str] = DEFAULT_NAMES, days: int = 365) -> dict[str, str]:
    """Write a CA and a certificate per role into ``directory``; return the paths by name.

    Keys are EC P-256, certificates valid for ``days``, with ``names`` (DNS names or IP
    addresses) as subject alternative names. Private keys are written with mode 0600.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    directory = os.fspath(directory)
    os.makedirs(directory, exist_ok=True)
    now = dt.datetime.now(dt.timezone.utc)
    names = list(names)

    def write(name: str, key, cert) -> None:
        key_path = os.path.join(directory, f"{name}-key.pem")
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
        with open(os.path.join(directory, f"{name}.pem"), "wb") as f:
            f.write(cert.public_bytes(serialization.Encoding.PEM))

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "geocoder cluster CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    write("ca", ca_key, ca)
    for role in ROLES:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"geocoder {role}")]))
            .issuer_name(ca_name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(_san(names), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        write(role, key, cert)
    return paths(directory)


def paths(directory: str | os.PathLike) -> dict[str, str]:
    """The certificate files of ``directory`` by name (``ca``, ``scheduler``, ``scheduler-key``, ...)."""
    directory = os.path.abspath(os.fspath(directory))
    out = {"ca": os.path.join(directory, "ca.pem")}
    for role in ROLES:
        out[role] = os.path.join(directory, f"{role}.pem")
        out[f"{role}-key"] = os.path.join(directory, f"{role}-key.pem")
    return out


def role_args(directory: str | os.PathLike, role: str) -> list[str]:
    """Command-line TLS flags of ``dask scheduler`` / ``dask worker`` for ``role``."""
    p = paths(directory)
    return ["--tls-ca-file", p["ca"], "--tls-cert", p[role], "--tls-key", p[f"{role}-key"]]


def client_security(directory: str | os.PathLike):
    """A :class:`distributed.Security` for a client holding the cluster's client certificate."""
    from distributed import Security

    p = paths(directory)
    missing = [f for f in (p["ca"], p["client"], p["client-key"]) if not os.path.exists(f)]
    if missing:
        from .errors import InputError

        raise InputError(missing[0], "TLS certificate file is missing (make them with 'geocoder cluster up --tls')")
    return Security(tls_ca_file=p["ca"], tls_client_cert=p["client"], tls_client_key=p["client-key"], require_encryption=True)
