"""Ed25519 signatures as strictly as libsodium checks them, since it is libsodium that checks
them (through PyNaCl), and the check a trust store makes on a public key when it loads one.

Why strict: a cofactorless verifier such as OpenSSL's accepts, for a public key of small
order (the identity ``01 00..00``, all zeros, the points of order 2, 4 and 8, and their
non-canonical encodings), signatures that anyone can make without a private key: R a
small-order point and S = 0 hold whenever R encodes ``-[k]A``, one try in at most eight.
libsodium's ``crypto_sign_verify_detached`` (which ``VerifyKey.verify`` reaches through
``crypto_sign_open``) refuses such keys and such R, and more:

* ``S`` must be canonical: ``S < L``.
* The public key ``A`` and ``R`` must not be of small order (a list of encodings, the sign
  bit ignored), ``A`` must be canonical (y < p) and a point of the curve.
* Cofactorless: the signature holds when the canonical encoding of ``[S]B - [k]A`` equals
  the 32 bytes ``R``, ``k = SHA-512(R || A || M) mod L``. So a non-canonical R never holds.

:func:`weakness` is the key half of that check in pure Python: a config names a weak key
file when it loads it, without loading libsodium. PyNaCl (about 3.7 MB of resident memory)
is imported by :func:`verify` only, the first time a module checks an image.
"""

from __future__ import annotations

__all__ = ["PUBLIC_KEY_BYTES", "SIGNATURE_BYTES", "SMALL_ORDER_Y", "verify", "weakness"]

PUBLIC_KEY_BYTES = 32
SIGNATURE_BYTES = 64

#: The field prime, and the curve constant d = -121665/121666.
P = 2**255 - 19
D = -121665 * pow(121666, P - 2, P) % P
_Y_MASK = (1 << 255) - 1

#: The y coordinates of the eight points of small order and their order: the identity (1),
#: the point of order 2 (-1), two of order 4 (0) and four of order 8 (two values of y, each
#: with both signs of x). With the sign bit either way and with y + p where that fits in 255
#: bits (p, p + 1), these are the fourteen encodings libsodium's ``ge25519_has_small_order``
#: refuses.
SMALL_ORDER_Y = {
    1: 1,
    P - 1: 2,
    0: 4,
    2707385501144840649318225287225658788936804267575313519463743609750303402022: 8,
    55188659117513257062467267217118295137698188065244968500265048394206261417927: 8,
}


def verify(public_key: bytes, signature: bytes, message: bytes) -> bool:
    """True when ``signature`` (64 bytes: R, S) is ``public_key``'s Ed25519 signature of
    ``message`` by libsodium's strict check; False for any other input, weak keys, malformed
    signatures and keys that are no curve point included. Raises ValueError only for a
    public key that is not 32 bytes long, TypeError for arguments that are not bytes-like."""
    public_key, signature = bytes(memoryview(public_key)), bytes(memoryview(signature))
    message = bytes(memoryview(message))
    if len(public_key) != PUBLIC_KEY_BYTES:
        raise ValueError(f"an Ed25519 public key is {PUBLIC_KEY_BYTES} bytes, not {len(public_key)}")
    if len(signature) != SIGNATURE_BYTES:
        return False
    from nacl.exceptions import BadSignatureError
    from nacl.signing import VerifyKey

    try:
        VerifyKey(public_key).verify(message, signature)
    except BadSignatureError:
        return False
    return True


def weakness(public_key: bytes) -> str | None:
    """Why libsodium refuses every signature of ``public_key`` (a raw 32-byte key), or None
    for a key it may accept: a point of small order, an encoding that is not canonical, or
    no point of the curve."""
    if len(public_key) != PUBLIC_KEY_BYTES:
        return f"{len(public_key)} bytes, not {PUBLIC_KEY_BYTES}"
    n = int.from_bytes(public_key, "little")
    y = n & _Y_MASK
    order = SMALL_ORDER_Y.get(y % P)
    if order is not None:
        what = "all zeros, " if n == 0 else "the identity" if order == 1 else ""
        what += "" if order == 1 else f"order {order}"
        canonical = "" if y < P else ", not canonically encoded"
        return f"a point of small order ({what}{canonical}): anyone can forge its signatures, no private key needed"
    if y >= P:
        return "not a canonical encoding (its y coordinate is p or more)"
    u = (y * y - 1) % P
    v = (D * y * y + 1) % P  # never 0: d is not a square
    if pow(u * pow(v, P - 2, P), (P - 1) // 2, P) not in (0, 1):
        return "no point of the curve (no x for its y)"
    return None
