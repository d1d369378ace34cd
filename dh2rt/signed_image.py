"""Signed program images: what a module accepts into its flash (sans-IO but for key files).

A signed image wraps a program image (:mod:`dh2rt.lang.image`, canonical JSON) in a binary
header and an Ed25519 signature. All integers are big-endian::

    offset  size  field
         0     4  magic b"DH2S"
         4     1  format version (1)
         5     4  program version: u32, monotonic; a module refuses one lower than it runs
         9     6  program digest: blake2b-48 of the program image, as a Hello frame carries it
        15     8  key id: the first 8 bytes of SHA-256 of the signer's raw public key
        23     4  program length: u32, bytes of the program image
        27     4  body length: u32, bytes of the body
        31     n  body: the program image, raw deflate with format 1's preset dictionary
      31+n    64  signature: Ed25519 over bytes 0 .. 31+n (header and body)

The body decompresses to exactly the canonical JSON image, so a program loaded from a signed
image is the program compiled from its source: same ``image``, same ``hash``, same Hello
digest. The preset dictionary (the AST's node and field names) belongs to format version 1
and never changes; another dictionary needs another format version.

An image of today's unsigned format (``DH2IMG1``) reads as an *unsigned* image of version 0;
a module accepts one only when its configuration allows unsigned programs.

Signatures are checked by :mod:`dh2rt.ed25519`: libsodium's strict check, through PyNaCl
(imported the first time an image is verified), so a module that verifies images never
imports ``cryptography`` (7 MB of resident memory, OpenSSL). Signing, key generation and PEM
key files need ``cryptography`` (PyNaCl reads no PEM); it is imported inside the functions
that do those, so importing this module costs nothing. Keys travel as raw bytes (32-byte
private seed, 32-byte public key); key files hold PEM (PKCS#8 private, SubjectPublicKeyInfo
public) or the raw 32 bytes. A public key that libsodium would refuse (of small order, not
canonical, no curve point: :func:`dh2rt.ed25519.weakness`) is refused when it is read, so
that a trust store never names a key whose signatures anyone can forge.
"""

from __future__ import annotations

import hashlib
import os
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from dh2rt import ed25519
from dh2rt.errors import ImageError, KeyFileError, SignedImageError
from dh2rt.lang.image import MAGIC as PROGRAM_MAGIC
from dh2rt.lang.image import from_image
from dh2rt.wire.frame import program_digest

MAGIC = b"DH2S"
FORMAT_VERSION = 1
#: magic, format version, program version, program digest, key id, program length, body length
HEADER = struct.Struct(">4sBI6s8sII")
#: Each header field: name, offset, size (for error messages that name where bytes went wrong).
FIELDS = (
    ("magic", 0, 4),
    ("format version", 4, 1),
    ("program version", 5, 4),
    ("program digest", 9, 6),
    ("key id", 15, 8),
    ("program length", 23, 4),
    ("body length", 27, 4),
)
KEY_ID_BYTES = 8
KEY_BYTES = 32
SIGNATURE_BYTES = 64
MAX_VERSION = 2**32 - 1
#: The largest program image a signed image may carry (a module's flash is small).
MAX_PROGRAM_BYTES = 1 << 20

#: Format 1's preset deflate dictionary: the canonical image's magic and the AST's node and
#: field names, rarest first (deflate reaches the end of a dictionary most cheaply). Frozen:
#: images signed today must decompress in every later dh2rt that reads format 1.
_DICTIONARY_1 = b"".join(
    (
        PROGRAM_MAGIC,
        b'{"":"Program","consts":[],"hormones":[],"name":,"natives":[],"options":[],"receptors":[],'
        b'"sensors":[],"variables":[]',
        b'{"":"SensorDecl","name":',
        b'{"":"VarDecl","initial":,"name":',
        b'{"":"NativeDecl","name":,"params":[',
        b'{"":"PathArg","name":',
        b'{"":"Wildcard"}',
        b'{"":"TruePattern"}',
        b'{"":"Timer"}',
        b'{"":"Neg","operand":',
        b'{"":"Not","operand":',
        b'{"":"Or","left":,"right":',
        b'{"":"SensorRef","name":',
        b'{"":"SensorIs","name":,"op":,"value":',
        b'{"":"ReceptorIs","name":,"op":,"value":',
        b'{"":"StopPeriodic","name":',
        b'{"":"Periodic","hormone":,"period":,"target":',
        b'{"":"ViaAll"}',
        b'{"":"VarRef","name":',
        b'{"":"Bind","name":',
        b'{"":"VarIs","name":,"op":,"value":',
        b'{"":"NativeCall","args":[],"name":',
        b'{"":"ReceptorOp","name":,"verb":',
        b'{"":"SetVar","name":,"value":',
        b'{"":"ViaReply","path_var":',
        b'{"":"Const","name":"ClockCycle","value":',
        b'{"":"HormoneDecl","name":,"params":[{"":"Param","domain":[],"name":',
        b'{"":"TimerIs","op":"==","value":{"":"BinOp","left":,"op":"/","right":',
        b'{"":"HormoneIs","args":[],"name":,"negate":false,"path_var":null}',
        b',"status":"passive"},',
        b',"status":"active"},{"":"Receptor","actions":[{"":"SetDOF","joint":1,"value":',
        b'{"":"Emit","hormone":{"":"HormoneTerm","args":[{"":"Name","name":',
        b'"target":{"":"ViaConnector","name":"back"}},{"":"KeepAlive"}],"name":',
        b'"pattern":{"":"And","left":{"":"TypeIs","negate":false,"types":["T1"]},"right":',
        b'{"":"Num","value":',
    )
)


class Verdict(StrEnum):
    """What a module makes of an image. :func:`verify` gives the first four; :func:`examine`
    adds ``MALFORMED``; the flash adds ``ROLLBACK`` (it knows the version it runs)."""

    OK = "ok"
    UNSIGNED = "unsigned"
    TAMPERED = "tampered"
    WRONG_KEY = "wrong key"
    MALFORMED = "malformed"
    ROLLBACK = "rollback"


@dataclass(frozen=True, slots=True)
class SignedImage:
    """The fields of a parsed image. ``key_id`` and ``signature`` are None for an unsigned
    image (today's ``DH2IMG1`` format, read as format version 0 and program version 0)."""

    format_version: int
    version: int
    digest: bytes
    key_id: bytes | None
    program_length: int
    body: bytes
    signature: bytes | None
    #: The bytes the signature covers: header and body.
    signed_part: bytes
    #: The size of the whole image in bytes.
    size: int

    @property
    def signed(self) -> bool:
        return self.signature is not None

    def program(self) -> bytes:
        """The program image the body holds (what ``load_image`` compiles). Raises
        SignedImageError when the body does not decompress to the length and digest that
        the header states; call it on a verified image (a signature proves the bytes are
        the signer's, not that they make a program)."""
        if self.format_version == 0:
            return self.body
        program = _decompress(self.body, self.program_length)
        if program_digest(program) != self.digest:
            raise SignedImageError(
                f"signed image: the body does not match the program digest at offset 9 ({self.digest.hex()})"
            )
        return program


# ---------------------------------------------------------------- packing and parsing


def pack(program_image: bytes, version: int, private_key: bytes) -> bytes:
    """Sign ``program_image`` (canonical image bytes) as program version ``version`` with the
    raw 32-byte Ed25519 ``private_key``."""
    from_image(program_image)  # raises ImageError for anything but a program image
    if not 0 <= version <= MAX_VERSION:
        raise ImageError(f"program version {version} is outside 0..{MAX_VERSION}")
    if len(program_image) > MAX_PROGRAM_BYTES:
        raise ImageError(f"program image of {len(program_image)} bytes is over the {MAX_PROGRAM_BYTES}-byte limit")
    signed = signed_part(program_image, version, public_key(private_key))
    return signed + _sign(private_key, signed)


def signed_part(program_image: bytes, version: int, public: bytes) -> bytes:
    """The bytes a signature covers (header and body) of ``program_image`` as program
    version ``version`` signed by the raw public key ``public``: what an image is without
    its last 64 bytes."""
    body = _compress(program_image)
    header = HEADER.pack(
        MAGIC,
        FORMAT_VERSION,
        version,
        program_digest(program_image),
        key_id(public),
        len(program_image),
        len(body),
    )
    return header + body


def is_image_file(path: Path) -> bool:
    """True when the file ``path`` starts as an image does (signed or not): what a command
    that takes a ``.dh2`` source tells apart before it compiles bytes as text."""
    try:
        with path.open("rb") as fh:
            head = fh.read(len(PROGRAM_MAGIC))
    except OSError:
        return False
    return head.startswith((PROGRAM_MAGIC, MAGIC))


def parse(data: bytes) -> SignedImage:
    """Read an image's fields without checking its signature. Raises SignedImageError,
    naming the field and its offset, for bytes that are no image or are cut short."""
    if data.startswith(PROGRAM_MAGIC):
        return _unsigned(data)
    _check_header(data)
    _magic, fmt, version, digest, kid, program_length, body_length = HEADER.unpack_from(data)
    if fmt != FORMAT_VERSION:
        raise SignedImageError(f"signed image: format version {fmt} at offset 4 (this dh2rt reads {FORMAT_VERSION})")
    if not 0 < program_length <= MAX_PROGRAM_BYTES:
        raise SignedImageError(
            f"signed image: program length {program_length} at offset 23 is outside 1..{MAX_PROGRAM_BYTES}"
        )
    end = HEADER.size + body_length
    if len(data) < end:
        raise SignedImageError(
            f"signed image: cut short in the body at offset {len(data)} "
            f"(the body length at offset 27 says {body_length} bytes from offset {HEADER.size})"
        )
    if len(data) != end + SIGNATURE_BYTES:
        short = len(data) < end + SIGNATURE_BYTES
        where = "cut short in the signature" if short else "trailing bytes after the signature"
        raise SignedImageError(
            f"signed image: {where}: it runs from offset {end} for {SIGNATURE_BYTES} bytes, the image has {len(data)}"
        )
    return SignedImage(
        format_version=fmt,
        version=version,
        digest=digest,
        key_id=kid,
        program_length=program_length,
        body=bytes(data[HEADER.size : end]),
        signature=bytes(data[end:]),
        signed_part=bytes(data[:end]),
        size=len(data),
    )


def _unsigned(data: bytes) -> SignedImage:
    return SignedImage(
        format_version=0,
        version=0,
        digest=program_digest(data),
        key_id=None,
        program_length=len(data),
        body=bytes(data),
        signature=None,
        signed_part=b"",
        size=len(data),
    )


def _check_header(data: bytes) -> None:
    """Raise for bytes that do not start like a signed image, naming the first header field
    they do not reach."""
    if not data or data[: len(MAGIC)] != MAGIC[: len(data)]:
        raise SignedImageError(
            f"not a DH2 program image: {len(data)} bytes starting {bytes(data[:8])!r} "
            f"(a signed image starts with {MAGIC!r}, an unsigned one with {PROGRAM_MAGIC!r})"
        )
    for name, offset, size in FIELDS:
        if len(data) < offset + size:
            raise SignedImageError(
                f"signed image: cut short in the {name} at offset {offset} ({size} bytes; the image has {len(data)})"
            )


def _compress(program: bytes) -> bytes:
    c = zlib.compressobj(9, zlib.DEFLATED, -15, 9, zlib.Z_DEFAULT_STRATEGY, _DICTIONARY_1)
    return c.compress(program) + c.flush()


def _decompress(body: bytes, length: int) -> bytes:
    """Inflate ``body`` to exactly ``length`` bytes (never more: no decompression bomb)."""
    d = zlib.decompressobj(-15, zdict=_DICTIONARY_1)
    try:
        out = d.decompress(body, length + 1)
    except zlib.error as exc:
        raise SignedImageError(f"signed image: the body at offset {HEADER.size} does not decompress ({exc})") from None
    if len(out) != length or not d.eof or d.unused_data:
        raise SignedImageError(
            f"signed image: the body at offset {HEADER.size} does not decompress to the program length "
            f"at offset 23 ({length} bytes)"
        )
    return out


# ---------------------------------------------------------------- verification


def verify(signed: SignedImage, trust: Sequence[bytes]) -> Verdict:
    """Check the signature against the raw public keys of ``trust``: OK, UNSIGNED (no
    signature), WRONG_KEY (signed by a key not in ``trust``) or TAMPERED (the key is trusted
    but the signature does not match the bytes: they changed after signing)."""
    if signed.signature is None or signed.key_id is None:
        return Verdict.UNSIGNED
    keys = [k for k in trust if key_id(k) == signed.key_id]
    if not keys:
        return Verdict.WRONG_KEY
    if any(_signature_holds(k, signed.signature, signed.signed_part) for k in keys):
        return Verdict.OK
    return Verdict.TAMPERED


@dataclass(frozen=True, slots=True)
class Examination:
    """An image judged as a whole: the verdict, why, and (unless MALFORMED) its fields; the
    program image is there when the verdict is OK or UNSIGNED and the body decodes."""

    verdict: Verdict
    reason: str
    image: SignedImage | None = None
    program: bytes | None = None


def examine(data: bytes, trust: Sequence[bytes]) -> Examination:
    """Parse, verify and (when the signature holds or there is none) decode ``data``."""
    try:
        signed = parse(data)
    except SignedImageError as exc:
        return Examination(Verdict.MALFORMED, str(exc))
    verdict = verify(signed, trust)
    if verdict is Verdict.WRONG_KEY:
        return Examination(verdict, f"signed by key {describe_key_id(signed.key_id)}, not in the trust store", signed)
    if verdict is Verdict.TAMPERED:
        weak = [why for k in trust if key_id(k) == signed.key_id and (why := ed25519.weakness(k)) is not None]
        if weak:  # a trust store made without check_public_key
            kid = describe_key_id(signed.key_id)
            return Examination(verdict, f"signed for key {kid}, a weak key: {weak[0]}", signed)
        return Examination(
            verdict,
            f"the signature does not match the bytes (key {describe_key_id(signed.key_id)}): altered after signing",
            signed,
        )
    try:
        program = signed.program()
        from_image(program)
    except ImageError as exc:
        return Examination(Verdict.MALFORMED, str(exc), signed)
    if verdict is Verdict.UNSIGNED:
        return Examination(verdict, "no signature", signed, program)
    return Examination(verdict, f"signed by trusted key {describe_key_id(signed.key_id)}", signed, program)


def describe_key_id(kid: bytes | None) -> str:
    return "(none)" if kid is None else kid.hex()


def _signature_holds(public: bytes, signature: bytes, data: bytes) -> bool:
    return ed25519.verify(public, signature, data)


def _sign(private: bytes, data: bytes) -> bytes:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.from_private_bytes(_raw_key(private, "private")).sign(data)


# ---------------------------------------------------------------- keys


def new_private_key() -> bytes:
    """A fresh raw 32-byte Ed25519 private key."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.Raw, serialization.PrivateFormat.Raw, serialization.NoEncryption()
    )


def public_key(private: bytes) -> bytes:
    """The raw public key of a raw private key."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    key = Ed25519PrivateKey.from_private_bytes(_raw_key(private, "private"))
    return key.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id(public: bytes) -> bytes:
    """The 8-byte id of a raw public key: the first bytes of its SHA-256."""
    return hashlib.sha256(public).digest()[:KEY_ID_BYTES]


def private_key_pem(private: bytes) -> bytes:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.from_private_bytes(_raw_key(private, "private")).private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def public_key_pem(public: bytes) -> bytes:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    return Ed25519PublicKey.from_public_bytes(_raw_key(public, "public")).public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def decode_private_key(data: bytes) -> bytes:
    """The raw private key in ``data`` (PEM PKCS#8 or 32 raw bytes); KeyFileError otherwise."""
    if not data.lstrip().startswith(b"-----BEGIN"):
        return _raw_key(data, "private")
    if b"PUBLIC KEY" in data:
        raise KeyFileError("holds a public key; signing needs the private key (the file without .pub)")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:  # TypeError: encrypted with a password
        raise KeyFileError(f"not a readable PEM private key ({exc})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise KeyFileError(f"holds a {type(key).__name__}, not an Ed25519 key")
    return key.private_bytes(serialization.Encoding.Raw, serialization.PrivateFormat.Raw, serialization.NoEncryption())


def decode_public_key(data: bytes) -> bytes:
    """The raw public key in ``data`` (PEM SubjectPublicKeyInfo or 32 raw bytes); KeyFileError
    for anything else and for a weak key (:func:`check_public_key`)."""
    return check_public_key(_decode_public_key(data))


def check_public_key(public: bytes) -> bytes:
    """``public`` (a raw public key) when libsodium may accept signatures of it; KeyFileError
    for a key whose signatures it refuses, or anyone can forge (:func:`dh2rt.ed25519.weakness`)."""
    why = ed25519.weakness(_raw_key(public, "public"))
    if why is not None:
        raise KeyFileError(
            f"refused: a weak Ed25519 public key, {why}; a trust store lists the .pub file of dh2rt keys new"
        )
    return public


def _decode_public_key(data: bytes) -> bytes:
    if not data.lstrip().startswith(b"-----BEGIN"):
        return _raw_key(data, "public")
    if b"PRIVATE KEY" in data:
        raise KeyFileError("holds a private key; a trust store lists public keys (the .pub file)")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        key = serialization.load_pem_public_key(data)
    except ValueError as exc:
        raise KeyFileError(f"not a readable PEM public key ({exc})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise KeyFileError(f"holds a {type(key).__name__}, not an Ed25519 key")
    return key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def _raw_key(data: bytes, kind: str) -> bytes:
    if len(data) != KEY_BYTES:
        raise KeyFileError(f"not an Ed25519 {kind} key: {len(data)} bytes, neither PEM nor {KEY_BYTES} raw bytes")
    return bytes(data)


# ---------------------------------------------------------------- key files


def write_key_pair(path: Path) -> bytes:
    """Write a new key pair: ``path`` the private key (PEM, mode 0600, never over an existing
    file) and ``path.pub`` beside it the public key. Returns the key id. Raises OSError
    (FileExistsError if either file exists)."""
    pub_path = public_key_path(path)
    for existing in (path, pub_path):
        if existing.exists():
            raise FileExistsError(17, "File exists", str(existing))
    private = new_private_key()
    public = public_key(private)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        os.fchmod(f.fileno(), 0o600)  # whatever the umask
        f.write(private_key_pem(private))
    with pub_path.open("xb") as f:
        f.write(public_key_pem(public))
    return key_id(public)


def public_key_path(private_path: Path) -> Path:
    """Where ``write_key_pair`` puts the public key: ``KEY.pub`` beside ``KEY``."""
    return private_path.with_name(private_path.name + ".pub")


def read_private_key(path: Path) -> bytes:
    """The raw private key in the file ``path``; KeyFileError names the file, OSError if unreadable."""
    try:
        return decode_private_key(path.read_bytes())
    except KeyFileError as exc:
        raise KeyFileError(f"{path}: {exc}") from None


def read_public_key(path: Path) -> bytes:
    """The raw public key in the file ``path``; KeyFileError names the file, OSError if unreadable."""
    try:
        return decode_public_key(path.read_bytes())
    except KeyFileError as exc:
        raise KeyFileError(f"{path}: {exc}") from None
