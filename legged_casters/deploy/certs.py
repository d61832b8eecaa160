"""Certificates for a secured link (``--secure DIR`` on every deploy tool).

    python -m legged_casters.deploy.certs certs/                  # CA + robot, bridge, operator
    python -m legged_casters.deploy.certs certs/ --namespace go2b  # for another robot namespace
    python -m legged_casters.deploy.certs certs/ --roles operator --force   # re-issue one role

Writes a small certificate authority (``ca.pem``, ``ca.key``) and, for each role, a
certificate signed by it and its private key (``robot.pem``/``robot.key``,
``bridge.pem``/``bridge.key``, ``operator.pem``/``operator.key``). A directory that
already holds ``ca.pem`` and ``ca.key`` keeps its CA: new role certificates are signed
by it. The common name of a role's certificate is ``<role>.<namespace>``; zenoh's access
control (see :func:`legged_casters.deploy.transport.access_control`) grants each key
expression of the namespace to that name only.

Copy to each machine only what it needs: ``ca.pem`` and its own role's pair (the robot:
``robot.pem``/``robot.key``). ``ca.key`` signs new certificates: keep it off the robot.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROLES = ("robot", "bridge", "operator")
"""robot: sim_robot, fake_go2, go2_adapter (puts <ns>/state); bridge: puts <ns>/cmd;
operator: teleop (puts <ns>/operator)."""

CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_HOSTS = ("localhost", "127.0.0.1", "::1")


def _key_usage(signs_certificates: bool) -> x509.KeyUsage:
    """Digital signatures (TLS with EC keys), plus certificate and CRL signing for the CA."""
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=signs_certificates,
        crl_sign=signs_certificates,
        encipher_only=False,
        decipher_only=False,
    )


def cert_path(directory: str | Path, role: str) -> Path:
    return Path(directory) / f"{role}.pem"


def key_path(directory: str | Path, role: str) -> Path:
    return Path(directory) / f"{role}.key"


def common_name(role: str, namespace: str) -> str:
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got {role!r}")
    return f"{role}.{namespace.strip('/')}"


@dataclass
class Authority:
    cert: x509.Certificate
    key: ec.EllipticCurvePrivateKey


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _validity(days: float, backdate_days: float) -> tuple[dt.datetime, dt.datetime]:
    start = dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=backdate_days, minutes=5)
    return start, start + dt.timedelta(days=days)


def make_ca(directory: str | Path, name: str = "legged_casters CA", days: float = 3650.0) -> Authority:
    """A new self-signed CA in ``directory`` (ca.pem, ca.key), replacing any there."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    start, end = _validity(days, 0.0)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            _key_usage(signs_certificates=True),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_key(d / CA_KEY, key)
    _write_cert(d / CA_CERT, cert)
    return Authority(cert, key)


def load_ca(directory: str | Path) -> Authority:
    d = Path(directory)
    cert = x509.load_pem_x509_certificate((d / CA_CERT).read_bytes())
    key = serialization.load_pem_private_key((d / CA_KEY).read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{d / CA_KEY}: expected an EC private key")
    return Authority(cert, key)


def _san(hosts: tuple[str, ...] | list[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def make_role_cert(
    ca: Authority,
    directory: str | Path,
    role: str,
    namespace: str = "go2",
    days: float = 365.0,
    backdate_days: float = 0.0,
    hosts: tuple[str, ...] | list[str] = DEFAULT_HOSTS,
) -> Path:
    """Issue ``<role>.pem``/``<role>.key`` in ``directory``, signed by ``ca``, valid from
    ``backdate_days`` ago for ``days`` (a backdate longer than the validity makes an
    expired certificate, for tests). The certificate serves for both sides of a link
    (server and client authentication): any tool may --listen or --connect."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    start, end = _validity(days, backdate_days)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name(role, namespace))]))
        .issuer_name(ca.cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            _key_usage(signs_certificates=False),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .add_extension(_san(list(hosts)), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()), critical=False)
        .sign(ca.key, hashes.SHA256())
    )
    _write_key(key_path(d, role), key)
    _write_cert(cert_path(d, role), cert)
    return cert_path(d, role)


def make_all(
    directory: str | Path,
    namespace: str = "go2",
    roles: tuple[str, ...] | list[str] = ROLES,
    days: float = 365.0,
    backdate_days: float = 0.0,
    hosts: tuple[str, ...] | list[str] = DEFAULT_HOSTS,
) -> list[Path]:
    """The CA (kept if ``directory`` has one) and the given roles' certificates."""
    d = Path(directory)
    ca = load_ca(d) if (d / CA_CERT).is_file() and (d / CA_KEY).is_file() else make_ca(d)
    return [make_role_cert(ca, d, r, namespace, days, backdate_days, hosts) for r in roles]


def describe(path: str | Path) -> tuple[str, dt.datetime, dt.datetime]:
    """(common name, not valid before, not valid after) of a PEM certificate."""
    cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return (str(cn[0].value) if cn else ""), cert.not_valid_before_utc, cert.not_valid_after_utc


class MaterialError(ValueError):
    """A certificate or key file that TLS cannot use; the message names the file, what is
    wrong with it and how to fix it, in one line."""


def _read(path: Path, what: str, fix: str) -> bytes:
    if path.is_dir():
        raise MaterialError(f"{path} is a folder, not a file ({what} goes there); remove it, then {fix}")
    try:
        data = path.read_bytes()
    except PermissionError:
        raise MaterialError(f"{path} cannot be read by this user; give it read access (chmod/chown)") from None
    except OSError as err:
        raise MaterialError(f"{path} cannot be read ({err.strerror}); {fix}") from None
    if not data.strip():
        raise MaterialError(f"{path} is empty; {fix}")
    return data


def _certificates(path: Path, data: bytes, fix: str) -> list[x509.Certificate]:
    if b"-----BEGIN CERTIFICATE-----" not in data:
        raise MaterialError(f"{path} holds no PEM certificate (no -----BEGIN CERTIFICATE----- block); {fix}")
    try:
        return x509.load_pem_x509_certificates(data)
    except ValueError:
        raise MaterialError(f"{path}: its PEM certificate does not parse (damaged?); {fix}") from None


def _cn(cert: x509.Certificate) -> str:
    cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(cn[0].value) if cn else cert.subject.rfc4514_string()


def _is_ca(cert: x509.Certificate) -> bool:
    try:
        if not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca:
            return False
    except x509.ExtensionNotFound:
        return False
    try:
        return cert.extensions.get_extension_for_class(x509.KeyUsage).value.key_cert_sign
    except x509.ExtensionNotFound:
        return True


def _issued_by(cert: x509.Certificate, ca: x509.Certificate) -> bool:
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def _spki(public_key) -> bytes:
    return public_key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def check_material(directory: str | Path, role: str, namespace: str, now: dt.datetime | None = None) -> None:
    """Check the TLS material of ``role`` in ``directory`` before anything uses it:
    ``ca.pem`` is a current CA certificate, ``<role>.pem`` a current certificate for
    ``<role>.<namespace>`` signed by it, ``<role>.key`` an unencrypted private key that
    belongs to ``<role>.pem``. Raises MaterialError with the file, the fault and the fix in
    one line (missing files are the caller's to report: they get the copy instructions)."""
    d = Path(directory)
    make = f"python -m legged_casters.deploy.certs {d}"
    reissue = f"re-issue it: `{make} --roles {role} --force --namespace {namespace}`"
    ca_path, cert_path_, key_path_ = d / CA_CERT, cert_path(d, role), key_path(d, role)
    copy_ca = f"copy the ca.pem that `python -m legged_casters.deploy.certs` wrote with {role}.pem (their CA)"
    now = now or dt.datetime.now(dt.timezone.utc)

    ca_all = _certificates(ca_path, _read(ca_path, "the CA certificate ca.pem", copy_ca), copy_ca)
    cas = [c for c in ca_all if _is_ca(c)]
    if not cas:
        raise MaterialError(
            f"{ca_path} is not a CA certificate (it is {_cn(ca_all[0])!r}, which may not sign certificates: a "
            f"role's certificate?); {copy_ca}, not a role's .pem"
        )

    cert_data = _read(cert_path_, f"this {role}'s certificate {role}.pem", reissue)
    if b"-----BEGIN CERTIFICATE-----" not in cert_data:
        raise MaterialError(f"{cert_path_} is not a PEM certificate (no -----BEGIN CERTIFICATE----- block); {reissue}")
    try:
        cert = x509.load_pem_x509_certificate(cert_data)
    except ValueError:
        raise MaterialError(f"{cert_path_} is not a PEM certificate (it does not parse); {reissue}") from None
    cn, want = _cn(cert), common_name(role, namespace)
    if cn != want:
        raise MaterialError(
            f"{cert_path_} is for {cn!r}, but this {role} on --namespace {namespace} needs {want!r}: "
            f"`{make} --namespace {namespace}` (or use the --namespace it was made for)"
        )
    start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
    if not start <= now <= end:
        when = f"expired on {end:%Y-%m-%d %H:%M} UTC" if now > end else f"is valid only from {start:%Y-%m-%d %H:%M} UTC"
        raise MaterialError(f"{cert_path_} {when}; {reissue}")
    issuers = [c for c in cas if _issued_by(cert, c)]
    if not issuers:
        raise MaterialError(
            f"{cert_path_} is not signed by the CA in {ca_path} ({_cn(cas[0])!r}); {copy_ca}, or {reissue}"
        )
    ca = issuers[0]
    if not ca.not_valid_before_utc <= now <= ca.not_valid_after_utc:
        raise MaterialError(
            f"{ca_path} (the CA) is valid from {ca.not_valid_before_utc:%Y-%m-%d %H:%M} to "
            f"{ca.not_valid_after_utc:%Y-%m-%d %H:%M} UTC, not now; make a new CA and certificates: "
            f"`python -m legged_casters.deploy.certs NEWDIR --namespace {namespace}`"
        )

    pair = f"copy the {role}.key made with this {role}.pem, or {reissue} (both files)"
    key_data = _read(key_path_, f"this {role}'s private key {role}.key", pair)
    if b"PRIVATE KEY-----" not in key_data:
        raise MaterialError(f"{key_path_} holds no PEM private key (no -----BEGIN ... PRIVATE KEY----- block); {pair}")
    try:
        key = serialization.load_pem_private_key(key_data, password=None)
    except TypeError:
        raise MaterialError(f"{key_path_} is encrypted, and TLS here needs an unencrypted key; {reissue}") from None
    except (ValueError, UnsupportedAlgorithm):
        raise MaterialError(f"{key_path_}: its PEM private key does not parse (damaged?); {pair}") from None
    if _spki(key.public_key()) != _spki(cert.public_key()):
        raise MaterialError(f"{key_path_} is not the key of {cert_path_} (it belongs to another certificate); {pair}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="certs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("directory", type=Path)
    p.add_argument("--namespace", default="go2", help="robot namespace the certificates are for (default: go2)")
    p.add_argument("--roles", nargs="+", choices=ROLES, default=list(ROLES), help="roles to issue (default: all)")
    p.add_argument("--days", type=float, default=365.0, help="validity of the role certificates (default: 365)")
    p.add_argument(
        "--backdate-days", type=float, default=0.0, help="start the validity this many days ago (tests: expired)"
    )
    p.add_argument(
        "--host",
        action="append",
        default=[],
        help="extra DNS name or IP address for the certificates (added to localhost, 127.0.0.1, ::1)",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing role certificates")
    args = p.parse_args(argv)
    existing = [cert_path(args.directory, r) for r in args.roles if cert_path(args.directory, r).exists()]
    if existing and not args.force:
        print(
            f"certs: error: {', '.join(map(str, existing))} already exist; add --force to re-issue "
            "(the CA in the directory is kept)",
            file=sys.stderr,
        )
        return 2
    if args.days <= 0:
        print("certs: error: --days must be positive", file=sys.stderr)
        return 2
    new_ca = not (args.directory / CA_CERT).is_file()
    hosts = DEFAULT_HOSTS + tuple(args.host)
    paths = make_all(args.directory, args.namespace, args.roles, args.days, args.backdate_days, hosts)
    if new_ca:
        d = args.directory
        print(f"certs: new certificate authority {d / CA_CERT} (its key {d / CA_KEY} signs certificates: keep it safe)")
    for path in paths:
        cn, start, end = describe(path)
        print(
            f"certs: {path} (key {path.with_suffix('.key')}): {cn}, "
            f"valid {start:%Y-%m-%d %H:%M} to {end:%Y-%m-%d %H:%M} UTC"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
