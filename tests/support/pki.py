"""Certificates made for a test: a CA, a server for 127.0.0.1, a client, a rogue CA's client (TLS tests)."""

from __future__ import annotations

import datetime
import ipaddress
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID


def _name(common: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common)])


def _write(path: Path, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> tuple[Path, Path]:
    cert_path, key_path = path.with_suffix(".crt"), path.with_suffix(".key")
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return cert_path, key_path


def make_pki(folder: Path) -> dict[str, Path]:
    """A CA, a server certificate for 127.0.0.1, a client certificate, and a rogue CA's client."""
    now = datetime.datetime.now(datetime.UTC)

    def issue(
        subject: str, issuer: x509.Name, signer: ec.EllipticCurvePrivateKey | None, ca: bool, server: bool
    ) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (
            x509.CertificateBuilder()
            .subject_name(_name(subject))
            .issuer_name(issuer)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
        )
        if server:
            builder = builder.add_extension(
                x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                critical=False,
            )
        return builder.sign(signer or key, hashes.SHA256()), key

    ca_cert, ca_key = issue("fleet CA", _name("fleet CA"), None, ca=True, server=False)
    rogue_cert, rogue_key = issue("rogue CA", _name("rogue CA"), None, ca=True, server=False)
    server = issue("gcs", ca_cert.subject, ca_key, ca=False, server=True)
    client = issue("drone-1", ca_cert.subject, ca_key, ca=False, server=False)
    impostor = issue("drone-1", rogue_cert.subject, rogue_key, ca=False, server=False)
    paths: dict[str, Path] = {}
    paths["ca"], _ = _write(folder / "ca", ca_cert, ca_key)
    paths["server_cert"], paths["server_key"] = _write(folder / "server", *server)
    paths["client_cert"], paths["client_key"] = _write(folder / "client", *client)
    paths["impostor_cert"], paths["impostor_key"] = _write(folder / "impostor", *impostor)
    return paths
