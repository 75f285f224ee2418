"""A system CA and the certificates of every host and role, for Zenoh mTLS (``rra certs``).

Layout of the output folder::

    ca/ca.pem, ca/ca.key            the system CA (the key stays with the operator)
    <host>/ca.pem                   for each host: the folder one copies to that machine
    <host>/agent.pem, agent.key     CN agent.<host>   the host agent (its Zenoh router)
    <host>/engine.pem, engine.key   CN engine.<host>  the engines it runs
    <host>/node.pem, node.key       CN node.<host>    the component nodes it runs
    operator/ca.pem, operator.pem, operator.key       CN operator (rra status/param/up tools)

Keys are ECDSA P-256 in PKCS#8 (what Zenoh's rustls loads), private keys mode 0600. Every
leaf certificate is for both TLS server and client authentication and names localhost,
127.0.0.1, ::1, its host's name and the ``--san`` addresses of its host, so routers can
verify each other's names. The access-control configuration (`rra_agent.security.acl`)
tells the roles apart by the common name.

`issue` is idempotent: an existing CA is reused, and a leaf certificate is kept while it is
signed by that CA, names everything it must, matches its key and is not close to expiry;
anything missing or stale is (re)written.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rra_agent.errors import RraError
from rra_agent.files import write_atomic

#: Roles with a certificate per host, and the one role that is not tied to a host.
HOST_ROLES = ("agent", "engine", "node")
OPERATOR = "operator"
CA_DIR = "ca"
DEFAULT_DAYS = 365
#: The CA outlives the leaves it signs: ten times their validity, at least ten years.
CA_DAYS_FACTOR = 10
CA_MIN_DAYS = 3650
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")
_DNS = re.compile(r"^[A-Za-z0-9_](?:[A-Za-z0-9_.\-]{0,251}[A-Za-z0-9_])?$")
_LOCAL_SANS = ("localhost", "127.0.0.1", "::1")

San = x509.DNSName | x509.IPAddress


def common_name(role: str, host: str | None = None) -> str:
    """``agent.<host>``, ``engine.<host>``, ``node.<host>`` or ``operator``."""
    return OPERATOR if role == OPERATOR else f"{role}.{host}"


def parse_san(text: str) -> tuple[str, list[str]]:
    """``HOST=ADDR[,ADDR...]`` -> (host, addresses); RraError if it is not that shape."""
    host, sep, addrs = text.partition("=")
    values = [a.strip() for a in addrs.split(",") if a.strip()]
    if not sep or not host or not values:
        raise RraError(f"--san {text!r}: expected HOST=ADDR[,ADDR...], e.g. robot=10.0.0.2")
    for a in values:
        _san(a)
    return host, values


def _san(addr: str) -> San:
    try:
        return x509.IPAddress(ipaddress.ip_address(addr))
    except ValueError:
        pass
    if not _DNS.match(addr):
        raise RraError(f"{addr!r} is neither an IP address nor a DNS name")
    return x509.DNSName(addr)


def _sans(host: str | None, extra: Iterable[str]) -> list[San]:
    names = [*_LOCAL_SANS, *([host] if host and _DNS.match(host) else []), *extra]
    out: list[San] = []
    for name in names:
        san = _san(name)
        if san not in out:
            out.append(san)
    return out


@dataclass(frozen=True)
class Issued:
    """What `issue` did with one file: ``wrote``, ``renewed`` or ``kept``."""

    action: str
    path: Path
    note: str = ""

    def line(self) -> str:
        return f"{self.action:7} {self.path}" + (f"  ({self.note})" if self.note else "")


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _read_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as e:
        raise RraError(f"{path}: not a readable PEM certificate ({e})") from None


def _read_key(path: Path) -> ec.EllipticCurvePrivateKey:
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as e:
        raise RraError(f"{path}: not a readable unencrypted PEM private key ({e})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise RraError(f"{path}: not an EC private key")
    return key


def _same_key(cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> bool:
    pub = cert.public_key()
    return (
        isinstance(pub, ec.EllipticCurvePublicKey)
        and pub.public_numbers() == key.public_key().public_numbers()
    )


def _key_usage(*, ca: bool) -> x509.KeyUsage:
    """Signatures only; a CA also signs certificates and revocation lists."""
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def _name(cn: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "rra-agent"),
            x509.NameAttribute(NameOID.COMMON_NAME, cn),
        ]
    )


# ---- the CA ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Authority:
    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate

    @property
    def pem(self) -> bytes:
        return _cert_pem(self.cert)


def _make_ca(name: str, days: int, now: dt.datetime) -> Authority:
    key = _new_key()
    subject = _name(name)
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(hours=1))
        .not_valid_after(now + dt.timedelta(days=max(CA_MIN_DAYS, CA_DAYS_FACTOR * days)))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(ski, critical=False)
        .sign(key, hashes.SHA256())
    )
    return Authority(key, cert)


def load_or_make_ca(
    ca_dir: Path, name: str, days: int, now: dt.datetime
) -> tuple[Authority, list[Issued]]:
    """The CA in ``ca_dir`` (reused as is), or a new one if the folder has none."""
    cert_path, key_path = ca_dir / "ca.pem", ca_dir / "ca.key"
    if cert_path.exists() != key_path.exists():
        there, missing = (cert_path, key_path) if cert_path.exists() else (key_path, cert_path)
        raise RraError(
            f"{there} exists but {missing} does not: restore it, or move {ca_dir} away to make "
            "a new CA (every certificate is then re-issued and must be copied again)"
        )
    if cert_path.exists():
        ca = Authority(_read_key(key_path), _read_cert(cert_path))
        if not _same_key(ca.cert, ca.key):
            raise RraError(f"{key_path} is not the key of {cert_path}")
        if ca.cert.not_valid_after_utc <= now:
            raise RraError(
                f"the CA {cert_path} expired on {ca.cert.not_valid_after_utc:%Y-%m-%d}: move "
                f"{ca_dir} away to make a new one (every certificate must then be copied again)"
            )
        return ca, [Issued("kept", cert_path, "the system CA")]
    ca_dir.mkdir(parents=True, exist_ok=True)
    os.chmod(ca_dir, 0o700)
    ca = _make_ca(name, days, now)
    write_atomic(key_path, _key_pem(ca.key), 0o600)
    write_atomic(cert_path, ca.pem, 0o644)
    return ca, [
        Issued("wrote", key_path, "CA key: keep it with the operator, copy it nowhere"),
        Issued("wrote", cert_path, "the system CA"),
    ]


# ---- leaf certificates ----------------------------------------------------------------------
def _make_leaf(
    ca: Authority,
    cn: str,
    sans: Sequence[San],
    days: int,
    now: dt.datetime,
    key: ec.EllipticCurvePrivateKey,
) -> x509.Certificate:
    ca_ski = ca.cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    return (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(ca.cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(hours=1))
        .not_valid_after(min(now + dt.timedelta(days=days), ca.cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(list(sans)), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False
        )
        .sign(ca.key, hashes.SHA256())
    )


def stale_reason(
    cert_path: Path,
    key_path: Path,
    ca: Authority,
    cn: str,
    sans: Sequence[San],
    days: int,
    now: dt.datetime,
) -> str | None:
    """Why the certificate at ``cert_path`` must be (re)issued, or None if it is current."""
    if not cert_path.exists() or not key_path.exists():
        return "missing"
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError):
        return "unreadable"
    try:
        cert.verify_directly_issued_by(ca.cert)
    except (ValueError, TypeError, InvalidSignature):
        return "not signed by this CA"
    if not isinstance(key, ec.EllipticCurvePrivateKey) or not _same_key(cert, key):
        return "key does not match"
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if [a.value for a in names] != [cn]:
        return "wrong common name"
    try:
        have = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return "no subject alternative names"
    missing = [s for s in sans if s not in have]
    if missing:
        return "adds " + ", ".join(str(s.value) for s in missing)
    margin = dt.timedelta(days=min(30.0, days / 5))
    if cert.not_valid_after_utc - now < margin:
        return f"expires {cert.not_valid_after_utc:%Y-%m-%d}"
    return None


def _leaf(
    folder: Path,
    role: str,
    cn: str,
    sans: Sequence[San],
    ca: Authority,
    days: int,
    now: dt.datetime,
) -> list[Issued]:
    cert_path, key_path = folder / f"{role}.pem", folder / f"{role}.key"
    why = stale_reason(cert_path, key_path, ca, cn, sans, days, now)
    if why is None:
        os.chmod(key_path, 0o600)
        return [Issued("kept", cert_path, cn)]
    key = _new_key()
    cert = _make_leaf(ca, cn, sans, days, now, key)
    write_atomic(key_path, _key_pem(key), 0o600)
    write_atomic(cert_path, _cert_pem(cert), 0o644)
    action = "wrote" if why == "missing" else "renewed"
    note = cn if why == "missing" else f"{cn}: {why}"
    return [Issued(action, key_path), Issued(action, cert_path, note)]


def _ca_copy(folder: Path, ca: Authority) -> list[Issued]:
    path = folder / "ca.pem"
    if path.exists() and path.read_bytes() == ca.pem:
        return []
    write_atomic(path, ca.pem, 0o644)
    return [Issued("wrote", path, "copy of the system CA")]


def issue(
    out: str | Path,
    hosts: Sequence[str],
    *,
    sans: Mapping[str, Sequence[str]] | None = None,
    days: int = DEFAULT_DAYS,
    ca_name: str = "rra-agent system CA",
    now: dt.datetime | None = None,
) -> list[Issued]:
    """Make (or complete) the certificate folder ``out`` for ``hosts``; return what it did.

    ``sans``: extra addresses per host (what other hosts dial to reach its router).
    """
    out = Path(out)
    now = now or _now()
    sans = dict(sans or {})
    if days < 1:
        raise RraError(f"--days must be at least 1, got {days}")
    for host in hosts:
        if not _NAME.match(host):
            raise RraError(f"host name {host!r} cannot name a certificate folder")
        if host in (CA_DIR, OPERATOR):
            raise RraError(f"a host named {host!r} would share DIR/{host}: rename the host")
    unknown = sorted(set(sans) - set(hosts))
    if unknown:
        raise RraError(
            f"--san for unknown host(s) {', '.join(unknown)} (hosts: {', '.join(hosts)})"
        )
    if out.exists() and not out.is_dir():
        raise RraError(f"{out} exists and is not a folder")
    ca, done = load_or_make_ca(out / CA_DIR, ca_name, days, now)
    for host in hosts:
        folder = out / host
        names = _sans(host, sans.get(host, ()))
        done += _ca_copy(folder, ca)
        for role in HOST_ROLES:
            done += _leaf(folder, role, common_name(role, host), names, ca, days, now)
    folder = out / OPERATOR
    done += _ca_copy(folder, ca)
    done += _leaf(folder, OPERATOR, OPERATOR, _sans(None, ()), ca, days, now)
    return done


def verify(cert_path: str | Path, ca_path: str | Path) -> x509.Certificate:
    """The certificate at ``cert_path`` if the CA at ``ca_path`` signed it and it is valid
    now; RraError otherwise."""
    cert, ca = _read_cert(Path(cert_path)), _read_cert(Path(ca_path))
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as e:
        raise RraError(f"{cert_path} is not signed by {ca_path} ({e or 'bad signature'})") from None
    now = _now()
    if not cert.not_valid_before_utc <= now < cert.not_valid_after_utc:
        raise RraError(f"{cert_path} is not valid now (until {cert.not_valid_after_utc:%Y-%m-%d})")
    return cert
