"""The mission's certificates: a mission CA and one certificate per participant.

Who is who. Every process that joins a secured mission's Zenoh network is a *participant* and holds a
certificate signed by the mission's own CA, with the participant's name as the certificate's common name
(CN). Names (`participants`):

    agent-<id>   the process of `flightstack agent --id <id>` (one per drone id)
    agents       a process hosting every agent (`sim`/`fly` with bus kind zenoh)
    world        `flightstack world` (the served simulation)
    operator     `flightstack abort` / `flightstack status`, and the signer of loopback aborts
    guard        `flightstack guard`

Which of them a mission has (decision, `participants`): `agent-<id>` for each of its drones, `operator`
and `guard` always; `agents` and `world` only when the mission's `bus.zenoh.endpoints` names them. The
shared `agents` certificate speaks for every drone, so a mission whose processes are one agent each must
not have one. A mission without a zenoh section runs in one process; its only Zenoh form is
`--bus zenoh`, which names `agents` (flightstack/cli/run.py), so it has `agents` and no `world`.

How names are verified (decision). Mutual TLS with `root_ca_certificate` = the mission CA: a peer
without a certificate signed by that CA cannot open a link at all. Zenoh's access control then binds
each key expression to the CN of the certificate on the link it arrives from (flightstack/comms/acl.py).
Host names and IP addresses are *not* verified (`verify_name_on_connect: false`, no IP subject
alternative names): lab computers get their addresses by DHCP, and an address says nothing about who
runs there. What an impostor listening on another participant's endpoint could do is limited by the
same ACL: on every link it is its own CN that decides what it may publish, so it can only publish its
own keys. The CA is per mission: a certificate of another mission (another CA) is refused.

Keys are EC P-256 (ECDSA with SHA-256). Private keys are written with mode 0600 and never
overwritten; the CA's key (`ca.key`) stays on the computer that ran `flightstack certs` (it signs, it is
never needed to fly). Layout of DIR:

    ca.pem, ca.key                      the mission CA (certificate, private key)
    <participant>.pem, <participant>.key  one pair per participant

Validity: `days` (default 90). `check_participant` reports the days left; preflight fails an expired
certificate and warns below `WARN_DAYS`.
"""

from __future__ import annotations

import datetime as dt
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

if TYPE_CHECKING:
    from collections.abc import Iterable

CA_NAME = "ca"
OPERATOR = "operator"
WORLD = "world"
GUARD = "guard"
AGENTS = "agents"
WARN_DAYS = 7
_SKEW = dt.timedelta(minutes=10)  # certificates start 10 min in the past: lab clocks are not exact


class CertError(ValueError):
    """A certificate directory, file or certificate that cannot be used; the message says which and why."""


def agent_name(drone_id: int) -> str:
    """The participant name (certificate CN) of the agent process of drone `drone_id`."""
    return f"agent-{drone_id}"


def participant_name(participant: str) -> str:
    """Certificate CN of a bus participant as `factory.make_bus` names it: a drone id "3" → "agent-3";
    "agents", "world", "operator", "guard" unchanged."""
    return agent_name(int(participant)) if participant.isdigit() else participant


def participants(drone_ids: Iterable[int], endpoint_names: Iterable[str] | None) -> list[str]:
    """Every participant of a mission with these drones, in a stable order (module docstring):
    `endpoint_names` are the names of its `bus.zenoh.endpoints`, None when it has no zenoh section."""
    named = {AGENTS} if endpoint_names is None else set(endpoint_names)
    shared = [n for n in (AGENTS, WORLD) if n in named]
    return [*(agent_name(i) for i in sorted(set(drone_ids))), *shared, OPERATOR, GUARD]


def is_participant_name(name: str) -> bool:
    """True for a name `participants` can return (`agent-<id>`, `agents`, `world`, `operator`, `guard`)."""
    return name in (AGENTS, WORLD, OPERATOR, GUARD) or (name.startswith("agent-") and name[6:].isdigit())


def any_participant_files(directory: Path) -> list[str]:
    """The certificate files of any possible participant (or the CA) that `directory` holds: what a
    `certs` run into it would clash with or leave behind."""
    files = sorted(directory.iterdir()) if directory.is_dir() else []
    return [
        p.name
        for p in files
        if p.suffix in (".pem", ".key") and (p.stem == CA_NAME or is_participant_name(p.stem))
    ]


@dataclass(frozen=True)
class ParticipantFiles:
    """The files one participant needs: the mission CA certificate, its certificate and private key."""

    ca: Path
    cert: Path
    key: Path


def files_of(directory: Path, participant: str) -> ParticipantFiles:
    return ParticipantFiles(
        directory / f"{CA_NAME}.pem", directory / f"{participant}.pem", directory / f"{participant}.key"
    )


def _name(cn: str, mission: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "flightstack"),
            x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, mission),
            x509.NameAttribute(NameOID.COMMON_NAME, cn),
        ]
    )


def _write_new(path: Path, data: bytes, mode: int) -> None:
    """Create `path` with `mode` (never overwrite: FileExistsError); the mode holds from creation on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.fchmod(fd, mode)  # the umask may have cleared bits of `mode` at creation
        os.write(fd, data)
    finally:
        os.close(fd)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _key_usage(ca: bool) -> x509.KeyUsage:
    """A CA signs certificates (and CRLs); a participant signs its TLS handshakes and aborts."""
    unused = ("content_commitment", "key_encipherment", "data_encipherment", "encipher_only")
    flags = dict.fromkeys((*unused, "key_agreement", "decipher_only"), False)
    return x509.KeyUsage(digital_signature=not ca, key_cert_sign=ca, crl_sign=ca, **flags)


def _ca(mission: str, now: dt.datetime, days: int) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(f"{mission} mission CA", mission)
    usage = _key_usage(ca=True)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _SKEW)
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(usage, critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def _leaf(
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    cn: str,
    mission: str,
    now: dt.datetime,
    days: int,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = ec.generate_private_key(ec.SECP256R1())
    usage = _key_usage(ca=False)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(cn, mission))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _SKEW)
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(usage, critical=True)
        # every participant both listens (server) and connects (client): mutual TLS needs both
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        # rustls (zenoh's TLS) requires a subject alternative name on a server certificate even when
        # names are not verified; the participant's name is a DNS-style name, never an address
        .add_extension(x509.SubjectAlternativeName([x509.DNSName(cn)]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_cert.public_key()),  # type: ignore[arg-type]
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def create_mission_certs(mission: str, names: list[str], out: Path, days: int = 90) -> list[Path]:
    """Create the CA and the certificate and key of each participant `names` (`participants`) in `out`
    (created, mode 0700 if new).

    Refuses (CertError) when `out` holds any participant's or the CA's files, also of a participant not
    in `names`: certificates are never silently replaced, and a folder never keeps a pair (say `agents`,
    from a run before the mission dropped it) beside the pairs of a new CA (delete the directory to
    start over). Returns the files written."""
    if not 1 <= days <= 3650:
        raise CertError(f"--days: {days} is outside 1..3650")
    wrong = [n for n in names if not is_participant_name(n)]
    if wrong:
        raise CertError(
            f"{wrong[0]!r} is not a participant name (agent-<id>, agents, world, operator, guard)"
        )
    existing = any_participant_files(out)
    if existing:
        raise CertError(f"{out}: already holds {', '.join(existing)} (remove them to create new ones)")
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    names = list(dict.fromkeys(names))
    targets = [out / f"{CA_NAME}.pem", out / f"{CA_NAME}.key"]
    targets += [out / f"{n}{ext}" for n in names for ext in (".pem", ".key")]
    now = dt.datetime.now(dt.UTC)
    ca_key, ca_cert = _ca(mission, now, days)
    _write_new(out / f"{CA_NAME}.key", _key_pem(ca_key), 0o600)
    _write_new(out / f"{CA_NAME}.pem", _cert_pem(ca_cert), 0o644)
    for n in names:
        key, cert = _leaf(ca_key, ca_cert, n, mission, now, days)
        _write_new(out / f"{n}.key", _key_pem(key), 0o600)
        _write_new(out / f"{n}.pem", _cert_pem(cert), 0o644)
    return targets


@dataclass(frozen=True)
class CertStatus:
    """What `check_participant` found: the certificate's CN, mission and expiry."""

    participant: str
    mission: str
    not_after: dt.datetime
    days_left: float


def _read_cert(path: Path, what: str) -> x509.Certificate:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CertError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError as exc:
        raise CertError(f"{path}: not a PEM certificate ({exc})") from None


def _attr(cert: x509.Certificate, oid: x509.ObjectIdentifier) -> str:
    vals = cert.subject.get_attributes_for_oid(oid)
    return str(vals[0].value) if vals else ""


def check_participant(
    directory: Path, participant: str, mission: str, now: dt.datetime | None = None
) -> CertStatus:
    """Check the files of `participant` in `directory` for `mission`; CertError naming the file and the
    reason when a file is missing or unreadable, the key is readable by others (mode not 0600) or does
    not match the certificate, the certificate is not signed by the mission CA, names another
    participant or mission, is not valid yet, or has expired."""
    f = files_of(directory, participant)
    now = now or dt.datetime.now(dt.UTC)
    ca = _read_cert(f.ca, "mission CA certificate")
    cert = _read_cert(f.cert, f"certificate of {participant}")
    try:
        st = f.key.stat()
    except OSError as exc:
        raise CertError(f"{f.key}: cannot read the private key of {participant}: {exc.strerror}") from None
    if st.st_mode & 0o077:
        raise CertError(f"{f.key}: readable by others (mode {st.st_mode & 0o777:o}); chmod 600 it")
    try:
        key = serialization.load_pem_private_key(f.key.read_bytes(), password=None)
    except (ValueError, TypeError, OSError) as exc:
        raise CertError(f"{f.key}: not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.curve.name != "secp256r1":
        raise CertError(f"{f.key}: not an EC P-256 key")
    pub = cert.public_key()
    own = key.public_key().public_numbers()
    if not isinstance(pub, ec.EllipticCurvePublicKey) or pub.public_numbers() != own:
        raise CertError(f"{f.cert}: does not match the private key {f.key.name}")
    _check_issued(ca, f.ca, cert, f.cert, participant, mission, now)
    not_after = min(ca.not_valid_after_utc, cert.not_valid_after_utc)
    return CertStatus(participant, mission, not_after, (not_after - now).total_seconds() / 86400.0)


def _check_issued(
    ca: x509.Certificate,
    ca_path: Path,
    cert: x509.Certificate,
    cert_path: Path,
    participant: str,
    mission: str,
    now: dt.datetime,
) -> None:
    """CertError unless `cert` is signed by `ca`, issued to `participant` of `mission`, and both are
    valid at `now`."""
    ca_pub = ca.public_key()
    try:
        if not isinstance(ca_pub, ec.EllipticCurvePublicKey) or cert.signature_hash_algorithm is None:
            raise InvalidSignature
        ca_pub.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
    except InvalidSignature:
        raise CertError(f"{cert_path}: not signed by the mission CA {ca_path}") from None
    cn, ou = _attr(cert, NameOID.COMMON_NAME), _attr(cert, NameOID.ORGANIZATIONAL_UNIT_NAME)
    if cn != participant:
        raise CertError(f"{cert_path}: issued to {cn!r}, not to {participant!r}")
    if ou != mission:
        raise CertError(f"{cert_path}: issued for mission {ou!r}, not {mission!r}")
    for c, path in ((ca, ca_path), (cert, cert_path)):
        if now < c.not_valid_before_utc:
            raise CertError(f"{path}: not valid before {c.not_valid_before_utc:%Y-%m-%d %H:%M} UTC")
        if now >= c.not_valid_after_utc:
            raise CertError(f"{path}: expired on {c.not_valid_after_utc:%Y-%m-%d %H:%M} UTC")


def operator_public_key(directory: Path, mission: str) -> ec.EllipticCurvePublicKey:
    """The operator's public key from `operator.pem`, checked against the mission CA (`ca.pem`): what
    the loopback abort listener verifies signed aborts with (the private key is not needed)."""
    f = files_of(directory, OPERATOR)
    ca = _read_cert(f.ca, "mission CA certificate")
    cert = _read_cert(f.cert, "operator certificate")
    _check_issued(ca, f.ca, cert, f.cert, OPERATOR, mission, dt.datetime.now(dt.UTC))
    pub = cert.public_key()
    if not isinstance(pub, ec.EllipticCurvePublicKey):
        raise CertError(f"{f.cert}: not an EC key")
    return pub


def operator_private_key(directory: Path, mission: str) -> ec.EllipticCurvePrivateKey:
    """The operator's private key (checked like `check_participant`), to sign loopback aborts."""
    check_participant(directory, OPERATOR, mission)
    key = serialization.load_pem_private_key(files_of(directory, OPERATOR).key.read_bytes(), password=None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    return key


def sign(key: ec.EllipticCurvePrivateKey, data: bytes) -> bytes:
    """ECDSA P-256 / SHA-256 signature (DER) of `data`."""
    return key.sign(data, ec.ECDSA(hashes.SHA256()))


def verify(pub: ec.EllipticCurvePublicKey, data: bytes, signature: bytes) -> bool:
    """True when `signature` is `pub`'s signature of `data`; never raises."""
    try:
        pub.verify(signature, data, ec.ECDSA(hashes.SHA256()))
    except (InvalidSignature, ValueError, TypeError):
        return False
    return True


__all__ = [
    "AGENTS",
    "GUARD",
    "OPERATOR",
    "WARN_DAYS",
    "WORLD",
    "CertError",
    "CertStatus",
    "ParticipantFiles",
    "agent_name",
    "any_participant_files",
    "check_participant",
    "create_mission_certs",
    "files_of",
    "is_participant_name",
    "operator_private_key",
    "operator_public_key",
    "participant_name",
    "participants",
    "sign",
    "verify",
]
