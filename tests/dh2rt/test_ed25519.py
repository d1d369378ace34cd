"""dh2rt.ed25519: RFC 8032's test vectors, the same verdict as ``cryptography`` (OpenSSL) on
valid, altered and malformed signatures and keys, and a module that verifies images without
importing ``cryptography``."""

from __future__ import annotations

import hashlib
import random
import subprocess
import sys
from pathlib import Path

import pytest
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from dh2rt import ed25519
from dh2rt import signed_image as si
from dh2rt.program import CompiledProgram

ROOT = Path(__file__).resolve().parents[2]

# ---------------------------------------------------------------- RFC 8032, section 7.1

_MESSAGE_1024 = (
    "08b8b2b733424243760fe426a4b54908632110a66c2f6591eabd3345e3e4eb98fa6e264bf09efe12ee50f8f54e9f77b1"
    "e355f6c50544e23fb1433ddf73be84d879de7c0046dc4996d9e773f4bc9efe5738829adb26c81b37c93a1b270b20329d"
    "658675fc6ea534e0810a4432826bf58c941efb65d57a338bbd2e26640f89ffbc1a858efcb8550ee3a5e1998bd177e93a"
    "7363c344fe6b199ee5d02e82d522c4feba15452f80288a821a579116ec6dad2b3b310da903401aa62100ab5d1a36553e"
    "06203b33890cc9b832f79ef80560ccb9a39ce767967ed628c6ad573cb116dbefefd75499da96bd68a8a97b928a8bbc10"
    "3b6621fcde2beca1231d206be6cd9ec7aff6f6c94fcd7204ed3455c68c83f4a41da4af2b74ef5c53f1d8ac70bdcb7ed1"
    "85ce81bd84359d44254d95629e9855a94a7c1958d1f8ada5d0532ed8a5aa3fb2d17ba70eb6248e594e1a2297acbbb39d"
    "502f1a8c6eb6f1ce22b3de1a1f40cc24554119a831a9aad6079cad88425de6bde1a9187ebb6092cf67bf2b13fd65f270"
    "88d78b7e883c8759d2c4f5c65adb7553878ad575f9fad878e80a0c9ba63bcbcc2732e69485bbc9c90bfbd62481d9089b"
    "eccf80cfe2df16a2cf65bd92dd597b0707e0917af48bbb75fed413d238f5555a7a569d80c3414a8d0859dc65a46128ba"
    "b27af87a71314f318c782b23ebfe808b82b0ce26401d2e22f04d83d1255dc51addd3b75a2b1ae0784504df543af8969b"
    "e3ea7082ff7fc9888c144da2af58429ec96031dbcad3dad9af0dcbaaaf268cb8fcffead94f3c7ca495e056a9b47acdb7"
    "51fb73e666c6c655ade8297297d07ad1ba5e43f1bca32301651339e22904cc8c42f58c30c04aafdb038dda0847dd988d"
    "cda6f3bfd15c4b4c4525004aa06eeff8ca61783aacec57fb3d1f92b0fe2fd1a85f6724517b65e614ad6808d6f6ee34df"
    "f7310fdc82aebfd904b01e1dc54b2927094b2db68d6f903b68401adebf5a7e08d78ff4ef5d63653a65040cf9bfd4aca7"
    "984a74d37145986780fc0b16ac451649de6188a7dbdf191f64b5fc5e2ab47b57f7f7276cd419c17a3ca8e1b939ae49e4"
    "88acba6b965610b5480109c8b17b80e1b7b750dfc7598d5d5011fd2dcc5600a32ef5b52a1ecc820e308aa342721aac09"
    "43bf6686b64b2579376504ccc493d97e6aed3fb0f9cd71a43dd497f01f17c0e2cb3797aa2a2f256656168e6c496afc5f"
    "b93246f6b1116398a346f1a641f3b041e989f7914f90cc2c7fff357876e506b50d334ba77c225bc307ba537152f3f161"
    "0e4eafe595f6d9d90d11faa933a15ef1369546868a7f3a45a96768d40fd9d03412c091c6315cf4fde7cb68606937380d"
    "b2eaaa707b4c4185c32eddcdd306705e4dc1ffc872eeee475a64dfac86aba41c0618983f8741c5ef68d3a101e8a3b8ca"
    "c60c905c15fc910840b94c00a0b9d0"
)

#: name: (secret key, public key, message, signature), hex as RFC 8032 section 7.1 states them.
RFC_8032 = {
    "TEST 1": (
        "9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60",
        "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a",
        "",
        "e5564300c360ac729086e2cc806e828a84877f1eb8e5d974d873e06522490155"
        "5fb8821590a33bacc61e39701cf9b46bd25bf5f0595bbe24655141438e7a100b",
    ),
    "TEST 2": (
        "4ccd089b28ff96da9db6c346ec114e0f5b8a319f35aba624da8cf6ed4fb8a6fb",
        "3d4017c3e843895a92b70aa74d1b7ebc9c982ccf2ec4968cc0cd55f12af4660c",
        "72",
        "92a009a9f0d4cab8720e820b5f642540a2b27b5416503f8fb3762223ebdb69da"
        "085ac1e43e15996e458f3613d0f11d8c387b2eaeb4302aeeb00d291612bb0c00",
    ),
    "TEST 3": (
        "c5aa8df43f9f837bedb7442f31dcb7b166d38535076f094b85ce3a2e0b4458f7",
        "fc51cd8e6218a1a38da47ed00230f0580816ed13ba3303ac5deb911548908025",
        "af82",
        "6291d657deec24024827e69c3abe01a30ce548a284743a445e3680d7db5ac3ac"
        "18ff9b538d16f290ae67f760984dc6594a7c15e9716ed28dc027beceea1ec40a",
    ),
    "TEST 1024": (
        "f5e5767cf153319517630f226876b86c8160cc583bc013744c6bf255f5cc0ee5",
        "278117fc144c72340f67d0f2316e8386ceffbf2b2428c9c51fef7c597f1d426e",
        _MESSAGE_1024,
        "0aab4c900501b3e24d7cdf4663326a3a87df5e4843b2cbdb67cbf6e460fec350"
        "aa5371b1508f9f4528ecea23c436d94b5e8fcd4f681e30a6ac00a9704a188a03",
    ),
    "TEST SHA(abc)": (
        "833fe62409237b9d62ec77587520911e9a759cec1d19755b7da901b96dca3d42",
        "ec172b93ad5e563bf4932c70e1245034c35467ef2efd4d64ebf819683467e2bf",
        "ddaf35a193617abacc417349ae20413112e6fa4e89a97ea20a9eeee64b55d39a"
        "2192992a274fc1a836ba3c23a3feebbd454d4423643ce80e2a9ac94fa54ca49f",
        "dc2a4459e7369633a52b1bf277839a00201009a3efbf3ecb69bea2186c26b589"
        "09351fc9ac90b3ecfdfbc7c66431e0303dca179c138ac17ad9bef1177331a704",
    ),
}


def _raw_public(private: Ed25519PrivateKey) -> bytes:
    return private.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


@pytest.mark.parametrize("name", list(RFC_8032))
def test_the_rfc_8032_vectors_verify(name: str) -> None:
    secret, public, message, signature = (bytes.fromhex(h) for h in RFC_8032[name])
    if name == "TEST 1024":
        assert len(message) == 1023
    # the transcription is right: cryptography makes the same key and signature from the secret
    private = Ed25519PrivateKey.from_private_bytes(secret)
    assert (_raw_public(private), private.sign(message)) == (public, signature)
    assert ed25519.verify(public, signature, message)
    assert not ed25519.verify(public, signature, message + b"\0")
    assert not ed25519.verify(public, signature[:-1] + bytes([signature[-1] ^ 0x01]), message)
    assert not ed25519.verify(bytes(public[:-1]) + bytes([public[-1] ^ 0x01]), signature, message)


# ---------------------------------------------------------------- the same verdict as cryptography


def _openssl(public: bytes, signature: bytes, message: bytes) -> bool:
    try:
        Ed25519PublicKey.from_public_bytes(public).verify(signature, message)
    except InvalidSignature:
        return False
    return True


def _flip(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


def test_random_signatures_and_one_bit_changes_get_cryptographys_verdict() -> None:
    """300 keys and messages: the signature holds for both; one bit flipped in the signature,
    the message or the key gives both the same verdict (nearly always: refused)."""
    rng = random.Random(8032)
    refused = 0
    for i in range(300):
        private = Ed25519PrivateKey.from_private_bytes(rng.randbytes(32))
        public = _raw_public(private)
        message = rng.randbytes(rng.choice([0, 1, 31, 64, 200, 1000]))
        signature = private.sign(message)
        assert ed25519.verify(public, signature, message) and _openssl(public, signature, message), i
        part = i % 3
        if part == 0:
            cases = [(public, _flip(signature, rng.randrange(512)), message)]
        elif part == 1 and message:
            cases = [(public, signature, _flip(message, rng.randrange(8 * len(message))))]
        else:
            cases = [(_flip(public, rng.randrange(256)), signature, message)]
        for case in cases:
            ours, theirs = ed25519.verify(*case), _openssl(*case)
            assert ours == theirs, (i, case[0].hex(), case[1].hex(), case[2].hex())
            refused += not ours
    assert refused == 300


def test_random_garbage_gets_cryptographys_verdict() -> None:
    """Keys and signatures of random bytes: keys that are no point (about half), S >= L
    (about 15 in 16): both refuse the same ones for the same reasons."""
    rng = random.Random(25519)
    for _ in range(200):
        public, signature, message = rng.randbytes(32), rng.randbytes(64), rng.randbytes(10)
        assert ed25519.verify(public, signature, message) is _openssl(public, signature, message) is False


# ---------------------------------------------------------------- malleability and strictness

P = 2**255 - 19
L = 2**252 + 27742317777372353535851937790883648493
D = -121665 * pow(121666, P - 2, P) % P
BASE = (
    15112221349535400772501151409588531511454012693041857206046113283949847762202,
    46316835694926478169428394003475163141307993866256225615783033603165251855960,
)
Affine = tuple[int, int]

#: The eight points of small order, canonically encoded: the identity (y = 1), the point of
#: order 2 (y = -1), two of order 4 (y = 0) and four of order 8.
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


# Affine arithmetic, independent of dh2rt.ed25519, to build the points the cases need.
def _add(p: Affine, q: Affine) -> Affine:
    (x1, y1), (x2, y2) = p, q
    t = D * x1 * x2 * y1 * y2 % P
    inverse = pow((1 + t) * (1 - t), P - 2, P)  # of both denominators at once
    return (x1 * y2 + x2 * y1) * (1 - t) * inverse % P, (y1 * y2 + x1 * x2) * (1 + t) * inverse % P


def _mul(n: int, p: Affine) -> Affine:
    acc = (0, 1)
    for bit in bin(n)[2:]:
        acc = _add(acc, acc)
        if bit == "1":
            acc = _add(acc, p)
    return acc


def _encode(p: Affine) -> bytes:
    return (p[1] | (p[0] & 1) << 255).to_bytes(32, "little")


def _decode(data: bytes) -> Affine:
    """RFC 8032 5.1.3 for canonical encodings of points (the cases only decode those)."""
    n = int.from_bytes(data, "little")
    y = n & ((1 << 255) - 1)
    x2 = (y * y - 1) * pow(D * y * y + 1, P - 2, P) % P
    x = pow(x2, (P + 3) // 8, P)
    if x * x % P != x2:
        x = x * pow(2, (P - 1) // 4, P) % P
    assert x * x % P == x2 and y < P
    return (P - x if x & 1 != n >> 255 else x) % P, y


def _other_encodings(point: bytes) -> list[bytes]:
    """The non-canonical encodings of a canonically encoded point: y + p where it fits in
    255 bits, and the sign bit set where x = 0."""
    n = int.from_bytes(point, "little")
    y, sign = n & ((1 << 255) - 1), n >> 255
    ys = [y + P] if y + P < 2**255 else []
    signs = [1 - sign] if _decode(point)[0] == 0 else []
    out = [y2 | sign << 255 for y2 in ys] + [y | s << 255 for s in signs] + [y2 | s << 255 for y2 in ys for s in signs]
    return [v.to_bytes(32, "little") for v in out]


def _le(n: int) -> bytes:
    return n.to_bytes(32, "little")


def test_s_must_be_below_l() -> None:
    """S + L (and anything else >= L) is refused by both, though [S + L]B = [S]B."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 2"])
    s = int.from_bytes(signature[32:], "little")
    for big in (s + L, s + 2 * L, s + 15 * L, L, 2**256 - 1, s | 1 << 255):
        forged = signature[:32] + _le(big)
        assert not ed25519.verify(public, forged, message) and not _openssl(public, forged, message)
    assert ed25519.verify(public, signature, message)


def test_small_order_and_non_canonical_keys_and_r_get_cryptographys_verdict() -> None:
    """Every small-order key, canonical or not, against R of small order (canonical or not)
    and S in {0, 1, L-1, L}. What OpenSSL does and so dh2rt.ed25519: a key is decoded with
    y modulo p and a sign bit on x = 0 ignored (so these keys are not refused), R is
    compared as bytes with the canonical encoding of [S]B - [k]A (so a non-canonical R never
    holds). The identity as public key with R = identity and S = 0 holds for every message."""
    keys = [k for point in SMALL_ORDER for k in [point, *_other_encodings(point)]]
    rs = [r for point in SMALL_ORDER for r in [point, *_other_encodings(point)[:1]]]
    held = 0
    for public in keys:
        for r in rs:
            for s in (0, 1, L - 1, L):
                signature = r + _le(s)
                ours, theirs = ed25519.verify(public, signature, b"m"), _openssl(public, signature, b"m")
                assert ours == theirs, (public.hex(), signature.hex())
                held += ours
    assert held > 0
    identity, identity_signed = SMALL_ORDER[0], (1 | 1 << 255).to_bytes(32, "little")
    for public in (identity, identity_signed, _le(P + 1)):
        for message in (b"", b"any message at all"):
            assert ed25519.verify(public, identity + _le(0), message) and _openssl(public, identity + _le(0), message)
        assert not ed25519.verify(public, identity_signed + _le(0), b"")  # R: the identity, non-canonical
        assert not _openssl(public, identity_signed + _le(0), b"")


def test_a_small_order_component_is_not_multiplied_away() -> None:
    """Signatures made with the secret scalar for a key A = aB + T and R = [r]B + T2 (T, T2
    of small order), S = r + k a: the cofactored check [8][S]B = [8]R + [8][k]A holds for
    every one of them, the cofactorless one only when [k]T = -T2. OpenSSL checks
    cofactorless; so does dh2rt.ed25519, and both agree on each case."""
    rng = random.Random(8)
    message = b"a program image"
    held = total = 0
    for point in SMALL_ORDER:
        torsion = _decode(point)
        seed = rng.randbytes(32)
        a = int.from_bytes(hashlib.sha512(seed).digest()[:32], "little") & ((1 << 254) - 8) | 1 << 254
        real = _raw_public(Ed25519PrivateKey.from_private_bytes(seed))
        if point == SMALL_ORDER[0]:
            assert _encode(_mul(a, BASE)) == real  # a is the secret scalar
        r = rng.randrange(1, L)
        r_point = _mul(r, BASE)
        for public in (_encode(_add(_decode(real), torsion)), real):
            for other in SMALL_ORDER:
                big_r = _encode(_add(r_point, _decode(other)))
                k = int.from_bytes(hashlib.sha512(big_r + public + message).digest(), "little") % L
                signature = big_r + _le((r + k * a) % L)
                ours, theirs = ed25519.verify(public, signature, message), _openssl(public, signature, message)
                assert ours == theirs, (public.hex(), signature.hex())
                held += ours
                total += 1
    trivial = 8 + 1  # no torsion in A nor in R: the real key (and A + identity) with T2 the identity
    assert trivial < held < total


def test_points_off_the_curve_are_refused() -> None:
    """A key whose y has no x is refused; so is an R that is no point (no [S]B - [k]A
    encodes to it)."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 1"])
    off = next(_le(y) for y in range(2, 100) if not _on_curve(y))
    assert not ed25519.verify(off, signature, message) and not _openssl(off, signature, message)
    forged = off + signature[32:]
    assert not ed25519.verify(public, forged, message) and not _openssl(public, forged, message)


def _on_curve(y: int) -> bool:
    x2 = (y * y - 1) * pow(D * y * y + 1, P - 2, P) % P
    return pow(x2, (P - 1) // 2, P) in (0, 1)


def test_wrong_lengths_behave_as_in_cryptography() -> None:
    """A public key of the wrong length raises ValueError (cryptography's from_public_bytes
    does); a signature of the wrong length is no signature (False)."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 1"])
    for bad in (b"", public[:31], public + b"\0"):
        with pytest.raises(ValueError):
            ed25519.verify(bad, signature, message)
        with pytest.raises(ValueError):
            Ed25519PublicKey.from_public_bytes(bad)
    for bad in (b"", signature[:63], signature + b"\0"):
        assert not ed25519.verify(public, bad, message) and not _openssl(public, bad, message)


def test_the_base_point_constants() -> None:
    assert _mul(L, BASE) == (0, 1) and BASE == (ed25519.BASE_X, ed25519.BASE_Y)
    assert _encode(_mul(8, _decode(SMALL_ORDER[4]))) == SMALL_ORDER[0]


# ---------------------------------------------------------------- a module without cryptography


def test_a_module_verifies_images_without_importing_cryptography(caterpillar: CompiledProgram, tmp_path: Path) -> None:
    """Packed here (signing needs cryptography), examined in a fresh process as a module
    does it: OK, TAMPERED and WRONG_KEY, and cryptography never imported there."""
    private, other = si.new_private_key(), si.new_private_key()
    data = si.pack(caterpillar.image, 3, private)
    tampered = bytearray(data)
    tampered[40] ^= 0x04
    (tmp_path / "image").write_bytes(data)
    (tmp_path / "tampered").write_bytes(bytes(tampered))
    (tmp_path / "key").write_bytes(si.public_key(private))
    (tmp_path / "other").write_bytes(si.public_key(other))
    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "import firmware.flash.slots\n"
        "from dh2rt.signed_image import examine, parse, verify\n"
        f"d = Path({str(tmp_path)!r})\n"
        "image, tampered = (d / 'image').read_bytes(), (d / 'tampered').read_bytes()\n"
        "key, other = (d / 'key').read_bytes(), (d / 'other').read_bytes()\n"
        "print(examine(image, [key]).verdict, examine(tampered, [key]).verdict, examine(image, [other]).verdict,"
        " verify(parse(image), [other, key]))\n"
        "print('cryptography' in sys.modules, sorted(m for m in sys.modules if m.startswith('cryptography')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["ok tampered wrong key ok", "False []"]
