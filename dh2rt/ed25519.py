"""Ed25519 signature verification in pure Python (RFC 8032, section 5.1.7): what a module
needs to check a signed image without importing ``cryptography`` (7 MB of resident memory
for a check made a few times per power-up). Signing and key generation stay with
``cryptography`` on the developer's machine (:mod:`dh2rt.signed_image`).

The check is the one OpenSSL makes (``ossl_ed25519_verify`` in ``crypto/ec/curve25519.c``),
which ``cryptography`` calls, so the two agree on every input:

* ``S`` must be canonical: ``S < L`` (else no signature, whatever the rest).
* The public key ``A`` must decode to a curve point, decoded as OpenSSL's
  ``ge_frombytes_vartime`` does: bit 255 is the sign of x and the other 255 bits are y *taken
  modulo p* (a y in p..2**255-1 is not refused), and a sign bit set on a point whose x is 0
  is ignored. A key whose y has no x on the curve is refused. Small-order keys (the
  identity among them) are not refused: they decode, and then no signature but ones built
  for them holds.
* ``k = SHA-512(R || A || M) mod L``, over the bytes as given (a non-canonical key hashes
  as its own bytes).
* *Cofactorless*: the signature holds when the canonical encoding of ``[S]B - [k]A`` equals
  the 32 bytes ``R`` (OpenSSL compares encodings, it never decodes R). So an R that is no
  point, or a non-canonical encoding of one (y >= p, or x = 0 with the sign bit set), never
  matches. The cofactored check ``[8][S]B == [8]R + [8][k]A`` of RFC 8032 would accept more
  signatures from keys or R with a small-order component; it is not used.

Points are in extended twisted Edwards coordinates (X:Y:Z:T), x = X/Z, y = Y/Z, xy = T/Z,
with the complete addition and doubling formulas of RFC 8032 section 5.1.4, so every point
(small-order ones included) adds correctly. ``[S]B - [k]A`` is one double-scalar
multiplication (Straus: one chain of doublings, width-5 NAF digits for both scalars). No
I/O, stdlib only. Variable time: everything it handles is public.
"""

from __future__ import annotations

import functools
import hashlib

__all__ = ["PUBLIC_KEY_BYTES", "SIGNATURE_BYTES", "verify"]

PUBLIC_KEY_BYTES = 32
SIGNATURE_BYTES = 64

#: The field prime and the order of the base point's subgroup.
P = 2**255 - 19
L = 2**252 + 27742317777372353535851937790883648493
#: The curve constant d = -121665/121666 and twice it; a square root of -1.
D = -121665 * pow(121666, P - 2, P) % P
D2 = 2 * D % P
SQRT_M1 = pow(2, (P - 1) // 4, P)
_Y_MASK = (1 << 255) - 1

#: The base point B (y = 4/5, x even).
BASE_X = 15112221349535400772501151409588531511454012693041857206046113283949847762202
BASE_Y = 46316835694926478169428394003475163141307993866256225615783033603165251855960

#: NAF window width: digits are odd, |digit| < 2**(W-1); tables hold 1P, 3P, .., (2**(W-1)-1)P.
_W = 5

#: A point in extended coordinates (X, Y, Z, T).
Point = tuple[int, int, int, int]
#: A point made ready to be added (Y-X, Y+X, 2dT, 2Z), as RFC 8032's addition uses it.
Cached = tuple[int, int, int, int]


def verify(public_key: bytes, signature: bytes, message: bytes) -> bool:
    """True when ``signature`` (64 bytes: R, S) is ``public_key``'s Ed25519 signature of
    ``message``; False for any other input, malformed signatures and keys that are no curve
    point included. Raises ValueError only for a public key that is not 32 bytes long (as
    ``cryptography``'s ``Ed25519PublicKey.from_public_bytes`` does), TypeError for arguments
    that are not bytes-like."""
    public_key, signature = bytes(memoryview(public_key)), bytes(memoryview(signature))
    if len(public_key) != PUBLIC_KEY_BYTES:
        raise ValueError(f"an Ed25519 public key is {PUBLIC_KEY_BYTES} bytes, not {len(public_key)}")
    if len(signature) != SIGNATURE_BYTES:
        return False
    r = signature[:32]
    s = int.from_bytes(signature[32:], "little")
    if s >= L:
        return False
    tables = _key_tables(public_key)
    if tables is None:
        return False
    h = hashlib.sha512(r + public_key)
    h.update(message)
    k = int.from_bytes(h.digest(), "little") % L
    return _encode(*_double_scalar_mult(s, k, *tables)) == r


def _decode(data: bytes) -> Point | None:
    """The point of a 32-byte encoding, decoded as OpenSSL does (y modulo p, the sign bit
    ignored when x is 0); None when y has no x on the curve."""
    n = int.from_bytes(data, "little")
    sign = n >> 255
    y = (n & _Y_MASK) % P
    u = (y * y - 1) % P
    v = (D * y * y + 1) % P
    # x = sqrt(u/v) = u v^3 (u v^7)^((p-5)/8), then fixed by sqrt(-1) (RFC 8032 5.1.3)
    v3 = v * v * v % P
    x = u * v3 * pow(u * v3 * v3 * v, (P - 5) // 8, P) % P
    vxx = v * x * x % P
    if vxx != u:
        if (vxx + u) % P:  # v x^2 == -u: x * sqrt(-1) is the root
            return None
        x = x * SQRT_M1 % P
    if x & 1 != sign:
        x = (P - x) % P
    return (x, y, 1, x * y % P)


def _encode(x: int, y: int, z: int) -> bytes:
    """The canonical encoding of the point (X:Y:Z)."""
    zi = pow(z, P - 2, P)
    x = x * zi % P
    y = y * zi % P
    return (y | (x & 1) << 255).to_bytes(32, "little")


def _add(p: Point, q: Cached) -> Point:
    """p + q (RFC 8032 5.1.4: complete, so p == q and the identity need no special case)."""
    x1, y1, z1, t1 = p
    ymx, ypx, t2d, z2 = q
    a = (y1 - x1) * ymx % P
    b = (y1 + x1) * ypx % P
    c = t1 * t2d % P
    d = z1 * z2 % P
    e = b - a
    f = d - c
    g = d + c
    h = b + a
    return (e * f % P, g * h % P, f * g % P, e * h % P)


def _double(p: Point) -> Point:
    x1, y1, z1, _ = p
    a = x1 * x1 % P
    b = y1 * y1 % P
    c = 2 * z1 * z1 % P
    h = a + b
    xy = x1 + y1
    e = h - xy * xy % P
    g = a - b
    f = c + g
    return (e * f % P, g * h % P, f * g % P, e * h % P)


def _cache(p: Point) -> Cached:
    x, y, z, t = p
    return ((y - x) % P, (y + x) % P, t * D2 % P, 2 * z % P)


def _negate(q: Cached) -> Cached:
    ymx, ypx, t2d, z2 = q
    return (ypx, ymx, (P - t2d) % P, z2)


def _odd_multiples(p: Point) -> list[Cached]:
    """[1]p, [3]p, .., [2**(W-1) - 1]p, cached."""
    two_p = _cache(_double(p))
    out = [p]
    for _ in range(2 ** (_W - 2) - 1):
        out.append(_add(out[-1], two_p))
    return [_cache(q) for q in out]


def _naf(n: int) -> list[int]:
    """The width-W non-adjacent form of ``n`` >= 0, least significant digit first."""
    digits: list[int] = []
    full, half = 1 << _W, 1 << (_W - 1)
    while n:
        if n & 1:
            digit = n & (full - 1)
            if digit >= half:
                digit -= full
            n -= digit
        else:
            digit = 0
        digits.append(digit)
        n >>= 1
    return digits


_IDENTITY: Point = (0, 1, 1, 0)
_BASE_TABLE = _odd_multiples((BASE_X, BASE_Y, 1, BASE_X * BASE_Y % P))
_BASE_NEGATED = [_negate(c) for c in _BASE_TABLE]


@functools.lru_cache(maxsize=16)
def _key_tables(public_key: bytes) -> tuple[list[Cached], list[Cached]] | None:
    """The odd multiples of -A and of A for a public key A (None when it is no point),
    kept for the few keys of a trust store: a module checks each image against the same."""
    a = _decode(public_key)
    if a is None:
        return None
    x, y, z, t = a
    minus_a = _odd_multiples(((P - x) % P, y, z, (P - t) % P))
    return minus_a, [_negate(c) for c in minus_a]


def _double_scalar_mult(s: int, k: int, q_table: list[Cached], q_negated: list[Cached]) -> tuple[int, int, int]:
    """[s]B + [k]Q as (X:Y:Z), Q the point whose odd multiples ``q_table`` holds (and
    ``q_negated`` their negatives). The doubling of RFC 8032 5.1.4 is written out in the
    loop, so that it skips T when no addition follows (T is not returned); the additions
    are :func:`_add`."""
    s_digits, k_digits = _naf(s), _naf(k)
    n = max(len(s_digits), len(k_digits))
    s_digits += [0] * (n - len(s_digits))
    k_digits += [0] * (n - len(k_digits))
    b_table, b_negated = _BASE_TABLE, _BASE_NEGATED
    x1, y1, z1, t1 = _IDENTITY
    started = False
    for i in range(n - 1, -1, -1):
        ds, dk = s_digits[i], k_digits[i]
        if started:
            a = x1 * x1 % P
            b = y1 * y1 % P
            c = 2 * z1 * z1 % P
            h = a + b
            xy = x1 + y1
            e = h - xy * xy % P
            g = a - b
            f = c + g
            x1 = e * f % P
            y1 = g * h % P
            z1 = f * g % P
            if ds or dk:
                t1 = e * h % P
        if ds:
            x1, y1, z1, t1 = _add((x1, y1, z1, t1), b_table[ds >> 1] if ds > 0 else b_negated[-ds >> 1])
            started = True
        if dk:
            x1, y1, z1, t1 = _add((x1, y1, z1, t1), q_table[dk >> 1] if dk > 0 else q_negated[-dk >> 1])
            started = True
    return x1, y1, z1
