"""Signed images forged without a private key, for the public keys of small order (issue 27).

For a key A of small order, R a point of small order and S = 0, the cofactorless check
(OpenSSL's, and dh2rt's own verifier's before issue 27) asks that R encode ``[0]B - [k]A =
[-k mod 8]A``, k = SHA-512(R || A || M) mod L: one of the eight small-order R does for about
two messages in three, and the program version changes the message until one does. Every
forgery made here is checked against OpenSSL (``cryptography``), which accepts it: libsodium,
and so dh2rt, must refuse it.

Affine Edwards arithmetic, independent of dh2rt; it only handles points of small order.
"""

from __future__ import annotations

import hashlib

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from dh2rt import signed_image as si

P = 2**255 - 19
L = 2**252 + 27742317777372353535851937790883648493
D = -121665 * pow(121666, P - 2, P) % P
Affine = tuple[int, int]

#: The eight points of small order, canonically encoded: the identity, the point of order 2,
#: the two of order 4 and the four of order 8.
SMALL_ORDER = [
    bytes.fromhex(h)
    for h in (
        "0100000000000000000000000000000000000000000000000000000000000000",
        "ecffffffffffffffffffffffffffffffffffffffffffffffffffffffffffff7f",
        "0000000000000000000000000000000000000000000000000000000000000000",
        "0000000000000000000000000000000000000000000000000000000000000080",
        "26e8958fc2b227b045c3f489f2ef98f0d5dfac05d3c63339b13802886d53fc05",
        "26e8958fc2b227b045c3f489f2ef98f0d5dfac05d3c63339b13802886d53fc85",
        "c7176a703d4dd84fba3c0b760d10670f2a2053fa2c39ccc64ec7fd7792ac037a",
        "c7176a703d4dd84fba3c0b760d10670f2a2053fa2c39ccc64ec7fd7792ac03fa",
    )
]


def _le(n: int) -> bytes:
    return n.to_bytes(32, "little")


def other_encodings(point: bytes) -> list[bytes]:
    """The non-canonical encodings a cofactorless verifier (OpenSSL) decodes to the point of
    the canonical encoding ``point``: y + p where it fits in 255 bits, and the sign bit flipped
    where x = 0."""
    n = int.from_bytes(point, "little")
    y, sign = n & ((1 << 255) - 1), n >> 255
    ys = [y + P] if y + P < 2**255 else []
    signs = [1 - sign] if decode(point)[0] == 0 else []
    out = [y2 | sign << 255 for y2 in ys] + [y | s << 255 for s in signs] + [y2 | s << 255 for y2 in ys for s in signs]
    return [_le(v) for v in out]


def decode(data: bytes) -> Affine:
    """The point of an encoding as OpenSSL decodes it (y modulo p, the sign bit ignored on x = 0)."""
    n = int.from_bytes(data, "little")
    y = (n & ((1 << 255) - 1)) % P
    x2 = (y * y - 1) * pow(D * y * y + 1, P - 2, P) % P
    x = pow(x2, (P + 3) // 8, P)
    if x * x % P != x2:
        x = x * pow(2, (P - 1) // 4, P) % P
    assert x * x % P == x2, data.hex()
    return ((P - x) % P if x & 1 != n >> 255 else x), y


def add(p: Affine, q: Affine) -> Affine:
    (x1, y1), (x2, y2) = p, q
    t = D * x1 * x2 * y1 * y2 % P
    inverse = pow((1 + t) * (1 - t), P - 2, P)  # of both denominators at once
    return (x1 * y2 + x2 * y1) * (1 - t) * inverse % P, (y1 * y2 + x1 * x2) * (1 + t) * inverse % P


def mul(n: int, p: Affine) -> Affine:
    acc = (0, 1)
    for bit in bin(n)[2:]:
        acc = add(acc, acc)
        if bit == "1":
            acc = add(acc, p)
    return acc


def encode(p: Affine) -> bytes:
    return _le(p[1] | (p[0] & 1) << 255)


#: Every 32-byte string that decodes (y taken modulo p) to a point of small order: the eight
#: canonical encodings and six others (the identity and the points of order 2 and 4 with y
#: + p or the sign bit of x = 0). Named for test ids.
WEAK_KEYS = {
    f"order{order}-{i}-{key.hex()[:4]}{key.hex()[-2:]}": key
    for i, (order, key) in enumerate(
        (order, key)
        for order, point in zip((1, 2, 4, 4, 8, 8, 8, 8), SMALL_ORDER, strict=True)
        for key in (point, *other_encodings(point))
    )
}


def openssl_accepts(public: bytes, signature: bytes, message: bytes) -> bool:
    try:
        Ed25519PublicKey.from_public_bytes(public).verify(signature, message)
    except InvalidSignature:
        return False
    return True


def forge(program_image: bytes, public: bytes, first_version: int = 1) -> bytes:
    """A signed image of ``program_image`` whose key id is ``public``'s (a key of small order)
    and whose signature (R of small order, S = 0) a cofactorless verifier accepts; no private
    key. Its program version is the first from ``first_version`` for which one R does."""
    a = decode(public)
    assert mul(8, a) == (0, 1), "not a key of small order"
    for version in range(first_version, first_version + 200):
        signed = si.signed_part(program_image, version, public)
        for r in SMALL_ORDER:
            k = int.from_bytes(hashlib.sha512(r + public + signed).digest(), "little") % L
            if encode(mul(-k % 8, a)) == r:
                signature = r + _le(0)
                assert openssl_accepts(public, signature, signed)
                return signed + signature
    raise AssertionError(f"no forgery for {public.hex()} in 200 versions")  # about (1/3)**200
