"""Certificates for the link between the laptop's and the robot's routers (``ovamos certs``).

A private certificate authority (``init``) signs one key and certificate per role (``issue``):
the common name (CN) says who holds it, ``laptop``, ``robot`` (a fleet's robots: ``robot-<id>``,
:func:`ovamos.shared.bus.acl.robot_common_names`) or a tool such as ``operator``, and the routers' access
control (``deploy/zenoh/*-secure.json5``) grants each CN its keys.
Zenoh's TLS link then authenticates both ends (mTLS): a peer without a certificate of this CA
gets no session at all.

Files in the folder (PEM):

* ``ca.pem`` (the CA's certificate: every host needs it) and ``ca.key`` (its key: keep it on
  the machine that issues certificates, never on the robot);
* ``NAME.pem`` and ``NAME.key`` per issued role (the key stays on the host that plays it).

Keys are ECDSA P-256, written with mode 0600, in a folder made 0700. What every router and
service that uses a certificate runs at start-up (through :mod:`ovamos.shared.bus.zconfig`): a missing,
unreadable, not-yet-valid or expired certificate (:func:`check_certificate`), a key others can
read or that is not the certificate's (:func:`check_key`), a CA others can write
(:func:`check_ca`: whoever can replace it decides whom this host trusts) is each one clear error
that says what to do, not a link that silently never comes up.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.types import PrivateKeyTypes
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_CERT, CA_KEY = "ca.pem", "ca.key"
CA_DAYS, CERT_DAYS = 3650, 825
#: the modes ``ovamos certs`` writes: a key only its owner reads, a certificate anyone may read,
#: the folder (which holds the CA's key) its owner's alone
KEY_MODE, CERT_MODE, FOLDER_MODE = 0o600, 0o644, 0o700
#: a certificate with fewer days left than this is logged as a warning at start-up
EXPIRY_WARNING_DAYS = 30
_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,62}$")
_RESERVED = {"ca"}


class CertError(ValueError):
    """A certificate operation that cannot be done; the message says why and what to do."""


@dataclass(frozen=True)
class CertInfo:
    """What :func:`check_certificate` found in a valid certificate."""

    path: Path | str     # the file, or the endpoint a peer presented it at
    common_name: str
    not_before: dt.datetime
    not_after: dt.datetime
    hosts: tuple[str, ...]
    is_ca: bool

    def days_left(self, now: dt.datetime | None = None) -> int:
        """Whole days until it expires (logged at start-up, so an expiry is seen coming)."""
        return (self.not_after - (now or _now())).days

    def names(self, host: str) -> bool:
        """Whether ``host`` (an IP address or DNS name a peer reaches this holder at) is among the
        certificate's subject alternative names, as a TLS client checks it (``*.`` one label)."""
        host = host.lower().rstrip(".")
        for name in (h.lower() for h in self.hosts):
            if name == host or (name.startswith("*.") and host.partition(".")[2] == name[2:]):
                return True
        return False

    def describe(self) -> str:
        hosts = f", hosts {', '.join(self.hosts)}" if self.hosts else ""
        return (f"{self.path}: CN {self.common_name}, valid until {_when(self.not_after)} "
                f"({self.days_left()} days left){hosts}")


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def _when(t: dt.datetime) -> str:
    return t.astimezone(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _write(path: Path, data: bytes, private: bool) -> None:
    """Write a file; a key is created with mode 0600 (never world-readable, not even briefly)."""
    mode = KEY_MODE if private else CERT_MODE
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.chmod(path, mode)  # O_CREAT's mode does not apply to a file that already existed


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def check_name(name: str) -> str:
    """A role name usable as a CN and a file name: lower-case letters, digits, '-' and '_'."""
    if not _NAME.match(name) or name in _RESERVED:
        raise CertError(f"certificate name {name!r}: use lower-case letters, digits, '-' or '_' "
                        f"(e.g. laptop, robot, operator); 'ca' is the authority's own")
    return name


def init_ca(folder: Path, *, days: int = CA_DAYS, common_name: str = "ovamos CA") -> Path:
    """Create a CA in ``folder`` (made if missing); refuses to replace an existing one."""
    folder = Path(folder)
    existing = [folder / f for f in (CA_CERT, CA_KEY) if (folder / f).exists()]
    if existing:
        raise CertError(f"a CA already exists in {folder} ({', '.join(p.name for p in existing)}): "
                        f"certificates it issued would stop working if it were replaced; use another "
                        f"folder, or delete the files yourself to start over")
    if days <= 0:
        raise CertError("--days must be positive")
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, FOLDER_MODE)  # it will hold the CA's key; mkdir's mode is cut by the umask
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    cert = (x509.CertificateBuilder()
            .subject_name(_name(common_name)).issuer_name(_name(common_name))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write(folder / CA_KEY, _key_pem(key), private=True)
    _write(folder / CA_CERT, _cert_pem(cert), private=False)
    return folder / CA_CERT


def _san(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not re.match(r"^[A-Za-z0-9*]([A-Za-z0-9.-]*[A-Za-z0-9])?$", host):
        raise CertError(f"--host {host!r} is neither an IP address nor a DNS name")
    return x509.DNSName(host)


def load_ca(folder: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    folder = Path(folder)
    cert_path, key_path = folder / CA_CERT, folder / CA_KEY
    if not cert_path.is_file() or not key_path.is_file():
        missing = ", ".join(p.name for p in (cert_path, key_path) if not p.is_file())
        raise CertError(f"no CA in {folder} ({missing} missing): create one with "
                        f"`ovamos certs init {folder}`, or give the folder that has it")
    check_ca(cert_path)
    key = _load_key(key_path)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{key_path} is not an EC key made by `ovamos certs init`")
    return x509.load_pem_x509_certificate(cert_path.read_bytes()), key


def issue(folder: Path, name: str, *, hosts: tuple[str, ...] | list[str] = (), days: int = CERT_DAYS,
          force: bool = False, valid_from: dt.datetime | None = None) -> tuple[Path, Path]:
    """Sign a key and certificate for role ``name`` (the CN) with the CA in ``folder``.

    ``hosts`` are the addresses (IP or DNS) the holder is reached at: the router that listens
    on the link needs its address here, as the other end checks it. Returns (certificate, key).
    ``valid_from`` backdates the certificate (tests make expired ones with it).
    """
    folder = Path(folder)
    check_name(name)
    cert_path, key_path = folder / f"{name}.pem", folder / f"{name}.key"
    if not force and (cert_path.exists() or key_path.exists()):
        raise CertError(f"{cert_path} already exists: --force replaces it (the old key stops working "
                        f"once the hosts have the new files)")
    if days <= 0:
        raise CertError("--days must be positive")
    ca_cert, ca_key = load_ca(folder)
    start = valid_from or (_now() - dt.timedelta(minutes=5))
    end = min(start + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    key = ec.generate_private_key(ec.SECP256R1())
    builder = (x509.CertificateBuilder()
               .subject_name(_name(name)).issuer_name(ca_cert.subject)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(start).not_valid_after(end)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                            content_commitment=False, key_encipherment=False,
                                            data_encipherment=False, key_agreement=False,
                                            encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                     ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                              critical=False))
    names = [_san(h) for h in dict.fromkeys(hosts)] or [x509.DNSName(name)]
    builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    _write(key_path, _key_pem(key), private=True)
    _write(cert_path, _cert_pem(cert), private=False)
    return cert_path, key_path


def check_certificate(path: str | Path, *, now: dt.datetime | None = None) -> CertInfo:
    """Read ``path`` and check that it is valid now; :class:`CertError` with the dates otherwise."""
    path = Path(path)
    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
    except FileNotFoundError:
        how = "`ovamos certs init DIR`" if path.name == CA_CERT else "`ovamos certs issue DIR NAME`"
        raise CertError(f"certificate {path} does not exist (make it with {how}, or copy it here)") from None
    except (OSError, ValueError) as exc:
        raise CertError(f"cannot read certificate {path}: {exc}") from None
    info = certificate_info(cert, path)
    cn, start, end = info.common_name, info.not_before, info.not_after
    now = now or _now()
    if now > end:
        raise CertError(f"certificate {path} (CN {cn}) expired on {_when(end)}: issue a new one with "
                        f"`ovamos certs issue DIR {cn or 'NAME'} --force` and copy it to this host")
    if now < start:
        raise CertError(f"certificate {path} (CN {cn}) is not valid before {_when(start)} (is this "
                        f"host's clock right?)")
    return info


def certificate_info(cert: x509.Certificate, path: Path | str) -> CertInfo:
    """What a certificate says (not whether it is valid): a file's, or what a peer presented."""
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    cn = str(attrs[0].value) if attrs else ""
    try:
        basic = cert.extensions.get_extension_for_class(x509.BasicConstraints).value
        is_ca = basic.ca
    except x509.ExtensionNotFound:
        is_ca = False
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        hosts = tuple(str(v) for v in san.get_values_for_type(x509.IPAddress)) + \
            tuple(san.get_values_for_type(x509.DNSName))
    except x509.ExtensionNotFound:
        hosts = ()
    return CertInfo(path, cn, cert.not_valid_before_utc, cert.not_valid_after_utc, hosts, is_ca)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def check_ca(path: str | Path, *, now: dt.datetime | None = None) -> CertInfo:
    """:func:`check_certificate` for the CA every peer is checked against, which only its owner may
    write: anyone who can replace it can make this host trust certificates of their own."""
    path = Path(path)
    info = check_certificate(path, now=now)
    if not info.is_ca:
        raise CertError(f"{path} is not a CA certificate")
    if _mode(path) & 0o022:
        raise CertError(f"CA certificate {path} is writable by others (mode {_mode(path):04o}): whoever can "
                        f"replace it chooses whom this host trusts; run `chmod go-w {path}`")
    return info


def _load_key(path: Path) -> PrivateKeyTypes:
    """A private key file that exists, only its owner can read, and parses."""
    if not path.is_file():
        raise CertError(f"private key {path} does not exist (it is written beside the certificate by "
                        f"`ovamos certs issue`)")
    if _mode(path) & 0o077:
        raise CertError(f"private key {path} is open to others (mode {_mode(path):04o}): anyone who reads "
                        f"it can act as its certificate's holder; run `chmod {KEY_MODE:o} {path}`")
    try:
        return serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise CertError(f"cannot read private key {path}: {exc}") from None


def _public(key: PrivateKeyTypes | x509.Certificate) -> bytes:
    return key.public_key().public_bytes(serialization.Encoding.DER,
                                         serialization.PublicFormat.SubjectPublicKeyInfo)


def check_key(path: str | Path, cert: str | Path | None = None) -> None:
    """The private key exists, is its owner's alone and parses; with ``cert``, it is that
    certificate's key (a mismatched pair fails every handshake, and only the peer would say so)."""
    path = Path(path)
    key = _load_key(path)
    if cert is None:
        return
    try:
        certificate = x509.load_pem_x509_certificate(Path(cert).read_bytes())
    except (OSError, ValueError) as exc:
        raise CertError(f"cannot read certificate {cert}: {exc}") from None
    if _public(key) != _public(certificate):
        raise CertError(f"private key {path} is not the key of certificate {cert}: copy the pair "
                        f"`ovamos certs issue` wrote together (NAME.pem and NAME.key), or issue a new one")


def list_certificates(folder: Path) -> list[CertInfo | CertError]:
    """Every ``*.pem`` in ``folder``, checked (an invalid one as its error)."""
    out: list[CertInfo | CertError] = []
    for path in sorted(Path(folder).glob("*.pem")):
        try:
            out.append(check_certificate(path))
        except CertError as exc:
            out.append(exc)
    return out
