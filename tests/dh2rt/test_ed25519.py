"""dh2rt.ed25519: RFC 8032's test vectors, libsodium's verdict on the published edge cases
(Wycheproof, "Taming the many EdDSAs") and on valid, altered, malformed and forged signatures
and keys, the weak-key check a trust store makes, and a module that verifies images without
importing ``cryptography``."""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import json
import random
import subprocess
import sys
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from dh2rt import ed25519
from dh2rt import signed_image as si
from dh2rt.program import CompiledProgram
from tests.dh2rt.forgery import (
    SMALL_ORDER,
    WEAK_KEYS,
    add,
    decode,
    encode,
    mul,
    openssl_accepts,
    other_encodings,
)

ROOT = Path(__file__).resolve().parents[2]
VECTORS = Path(__file__).resolve().parent / "vectors"

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


# ---------------------------------------------------------------- libsodium's verdict

#: PyNaCl's own libsodium (its extension module exports libsodium's functions)
_SODIUM = ctypes.CDLL(str(getattr(importlib.util.find_spec("nacl._sodium"), "origin", None)))
_SODIUM.crypto_sign_verify_detached.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_ulonglong, ctypes.c_char_p]
_SODIUM.crypto_sign_verify_detached.restype = ctypes.c_int


def _libsodium(public: bytes, signature: bytes, message: bytes) -> bool:
    """libsodium's ``crypto_sign_verify_detached``, called directly (dh2rt goes through
    PyNaCl's ``VerifyKey.verify`` and ``crypto_sign_open``). It reads 64 bytes of signature
    and 32 of key: other lengths are no signature."""
    if len(public) != 32 or len(signature) != 64:
        return False
    return bool(_SODIUM.crypto_sign_verify_detached(signature, message, len(message), public) == 0)


def _vectors(name: str, key: str) -> list[dict[str, object]]:
    cases: list[dict[str, object]] = json.loads((VECTORS / name).read_text())[key]
    return cases


WYCHEPROOF = _vectors("wycheproof_ed25519.json", "tests")
SPECCHECK = _vectors("speccheck_cases.json", "cases")
#: "Taming the many EdDSAs", results.md: OpenSSL 3.0 accepts cases 0 to 3 and 11, as
#: dh2rt's own cofactorless verifier did before issue 27; libsodium accepts case 3 only.
OPENSSL_SPECCHECK = [True] * 4 + [False] * 7 + [True]


def _hex(case: dict[str, object], *names: str) -> tuple[bytes, ...]:
    return tuple(bytes.fromhex(str(case[n])) for n in names)


def test_the_vectors_are_all_there() -> None:
    assert len(WYCHEPROOF) == 151 and len(SPECCHECK) == 12
    assert sum(c["result"] == "valid" for c in WYCHEPROOF) == 88
    assert [c["libsodium"] for c in SPECCHECK] == [i == 3 for i in range(12)]


@pytest.mark.parametrize("case", WYCHEPROOF, ids=lambda c: f"tc{c['tcId']}")
def test_wycheproof_vectors_get_libsodiums_verdict(case: dict[str, object]) -> None:
    public, message, signature = _hex(case, "pk", "msg", "sig")
    expected = case["result"] == "valid"
    assert ed25519.verify(public, signature, message) is _libsodium(public, signature, message) is expected, case
    if ed25519.weakness(public) is not None:
        assert not expected


@pytest.mark.parametrize("case", SPECCHECK, ids=lambda c: f"case{c['case']}")
def test_taming_the_many_eddsas_cases_get_libsodiums_verdict(case: dict[str, object]) -> None:
    """The twelve cases of the paper: small-order A or R (0 to 2), mixed-order A and R
    (3 to 5, only 3 holds cofactorless), S >= L (6, 7), non-canonical A or R (8 to 11).
    OpenSSL, as the old verifier, accepts the ones of small order, which libsodium refuses."""
    public, message, signature = _hex(case, "pub_key", "message", "signature")
    i = int(str(case["case"]))
    assert ed25519.verify(public, signature, message) is _libsodium(public, signature, message) is case["libsodium"]
    assert openssl_accepts(public, signature, message) is OPENSSL_SPECCHECK[i]
    if i <= 2:
        assert ed25519.weakness(public) is not None or ed25519.weakness(signature[:32]) is not None


def _flip(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


def test_random_signatures_and_one_bit_changes_get_libsodiums_verdict() -> None:
    """300 keys and messages: the signature holds for both; one bit flipped in the signature,
    the message or the key gives both the same verdict (nearly always: refused)."""
    rng = random.Random(8032)
    refused = 0
    for i in range(300):
        private = Ed25519PrivateKey.from_private_bytes(rng.randbytes(32))
        public = _raw_public(private)
        message = rng.randbytes(rng.choice([0, 1, 31, 64, 200, 1000]))
        signature = private.sign(message)
        assert ed25519.verify(public, signature, message) and _libsodium(public, signature, message), i
        assert ed25519.weakness(public) is None
        part = i % 3
        if part == 0:
            case = (public, _flip(signature, rng.randrange(512)), message)
        elif part == 1 and message:
            case = (public, signature, _flip(message, rng.randrange(8 * len(message))))
        else:
            case = (_flip(public, rng.randrange(256)), signature, message)
        ours, theirs = ed25519.verify(*case), _libsodium(*case)
        assert ours == theirs, (i, case[0].hex(), case[1].hex(), case[2].hex())
        refused += not ours
    assert refused == 300


def test_random_garbage_gets_libsodiums_verdict() -> None:
    """Keys and signatures of random bytes (keys that are no point, about half; S >= L, about
    15 in 16), and signatures of the wrong length: refused by both."""
    rng = random.Random(25519)
    for _ in range(300):
        public, signature, message = rng.randbytes(32), rng.randbytes(64), rng.randbytes(10)
        assert ed25519.verify(public, signature, message) is _libsodium(public, signature, message) is False
        short = signature[: rng.randrange(64)]
        assert ed25519.verify(public, short, message) is False


# ---------------------------------------------------------------- malleability and strictness

P = 2**255 - 19
L = 2**252 + 27742317777372353535851937790883648493
BASE = (
    15112221349535400772501151409588531511454012693041857206046113283949847762202,
    46316835694926478169428394003475163141307993866256225615783033603165251855960,
)


def _le(n: int) -> bytes:
    return n.to_bytes(32, "little")


def test_s_must_be_below_l() -> None:
    """S + L (and anything else >= L) is refused, though [S + L]B = [S]B."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 2"])
    s = int.from_bytes(signature[32:], "little")
    for big in (s + L, s + 2 * L, s + 15 * L, L, 2**256 - 1, s | 1 << 255):
        forged = signature[:32] + _le(big)
        assert ed25519.verify(public, forged, message) is _libsodium(public, forged, message) is False
    assert ed25519.verify(public, signature, message)


def test_small_order_and_non_canonical_keys_and_r_are_refused() -> None:
    """Every small-order key, canonical or not, against R of small order (canonical or not)
    and S in {0, 1, L-1, L}: libsodium, and so dh2rt, refuses every one. OpenSSL (as dh2rt's
    own verifier did before issue 27) accepts some of them: the identity as public key with
    R = identity and S = 0 holds for every message there."""
    rs = [r for point in SMALL_ORDER for r in [point, *other_encodings(point)[:1]]]
    openssl_held = 0
    for public in WEAK_KEYS.values():
        for r in rs:
            for s in (0, 1, L - 1, L):
                signature = r + _le(s)
                assert ed25519.verify(public, signature, b"m") is _libsodium(public, signature, b"m") is False
                openssl_held += openssl_accepts(public, signature, b"m")
    assert openssl_held > 0
    identity = SMALL_ORDER[0]
    for message in (b"", b"any message at all"):
        assert openssl_accepts(identity, identity + _le(0), message)
        assert not ed25519.verify(identity, identity + _le(0), message)


def test_a_small_order_component_is_not_multiplied_away() -> None:
    """Signatures made with the secret scalar for a key A = aB + T and R = [r]B + T2 (T, T2
    of small order), S = r + k a: the cofactored check [8][S]B = [8]R + [8][k]A holds for
    every one of them, the cofactorless one only when [k]T = -T2. libsodium checks
    cofactorless and refuses neither such A nor such R (they are not of small order): dh2rt,
    libsodium and OpenSSL agree on each case."""
    rng = random.Random(8)
    message = b"a program image"
    held = total = 0
    for point in SMALL_ORDER:
        torsion = decode(point)
        seed = rng.randbytes(32)
        a = int.from_bytes(hashlib.sha512(seed).digest()[:32], "little") & ((1 << 254) - 8) | 1 << 254
        real = _raw_public(Ed25519PrivateKey.from_private_bytes(seed))
        if point == SMALL_ORDER[0]:
            assert encode(mul(a, BASE)) == real  # a is the secret scalar
        r = rng.randrange(1, L)
        r_point = mul(r, BASE)
        for public in (encode(add(decode(real), torsion)), real):
            for other in SMALL_ORDER:
                big_r = encode(add(r_point, decode(other)))
                k = int.from_bytes(hashlib.sha512(big_r + public + message).digest(), "little") % L
                signature = big_r + _le((r + k * a) % L)
                ours = ed25519.verify(public, signature, message)
                assert ours is _libsodium(public, signature, message) is openssl_accepts(public, signature, message)
                held += ours
                total += 1
    trivial = 8 + 1  # no torsion in A nor in R: the real key (and A + identity) with T2 the identity
    assert trivial < held < total


def test_points_off_the_curve_are_refused() -> None:
    """A key whose y has no x is refused, and named so by the weak-key check; so is an R that
    is no point (no [S]B - [k]A encodes to it)."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 1"])
    off = next(_le(y) for y in range(2, 100) if not _on_curve(y))
    assert ed25519.verify(off, signature, message) is _libsodium(off, signature, message) is False
    assert "no point of the curve" in str(ed25519.weakness(off))
    forged = off + signature[32:]
    assert ed25519.verify(public, forged, message) is _libsodium(public, forged, message) is False


def _on_curve(y: int) -> bool:
    """Whether some x makes (x, y) a point: tried by taking the square root."""
    try:
        decode(_le(y))
    except AssertionError:
        return False
    return True


def test_wrong_lengths() -> None:
    """A public key of the wrong length raises ValueError (as cryptography's
    from_public_bytes does); a signature of the wrong length is no signature (False)."""
    _, public, message, signature = (bytes.fromhex(h) for h in RFC_8032["TEST 1"])
    for bad in (b"", public[:31], public + b"\0"):
        with pytest.raises(ValueError):
            ed25519.verify(bad, signature, message)
        with pytest.raises(ValueError):
            Ed25519PublicKey.from_public_bytes(bad)
        assert ed25519.weakness(bad) is not None
    for bad in (b"", signature[:63], signature + b"\0"):
        assert not ed25519.verify(public, bad, message)


# ---------------------------------------------------------------- the weak-key check


def test_the_weak_keys_are_the_fourteen_encodings_of_small_order_points() -> None:
    """The eight points of small order (each [8]P is the identity) have fourteen encodings
    that a verifier taking y modulo p decodes; libsodium's list is exactly those, and
    dh2rt.ed25519.weakness names each as of small order."""
    listed = {
        _le(y + extra | sign << 255)
        for y in ed25519.SMALL_ORDER_Y
        for extra in (0, P)
        for sign in (0, 1)
        if y + extra < 2**255
    }
    assert listed == set(WEAK_KEYS.values()) and len(listed) == 14
    assert set(SMALL_ORDER) <= listed
    for key in listed:
        assert mul(8, decode(key)) == (0, 1)
        assert "small order" in str(ed25519.weakness(key)), key.hex()
    assert "all zeros" in str(ed25519.weakness(bytes(32)))
    assert "the identity" in str(ed25519.weakness(SMALL_ORDER[0]))


def test_the_weak_key_check_refuses_what_libsodium_refuses_and_only_that() -> None:
    """Non-canonical encodings (y >= p) and keys that are no point are weak; the keys of
    real signers are not, nor a key with a small-order component (A = aB + T, which
    libsodium accepts: the mixed-order cases above)."""
    for y in range(P, 2**255):
        for sign in (0, 1):
            assert ed25519.weakness(_le(y | sign << 255)) is not None
    rng = random.Random(27)
    for _ in range(200):
        assert ed25519.weakness(_raw_public(Ed25519PrivateKey.from_private_bytes(rng.randbytes(32)))) is None
        key = rng.randbytes(32)
        y = int.from_bytes(key, "little") & ((1 << 255) - 1)
        assert (ed25519.weakness(key) is None) is (y < P and _on_curve(y) and y % P not in ed25519.SMALL_ORDER_Y)
    mixed = encode(add(decode(_raw_public(Ed25519PrivateKey.from_private_bytes(bytes(32)))), decode(SMALL_ORDER[4])))
    assert ed25519.weakness(mixed) is None


# ---------------------------------------------------------------- a module without cryptography


def test_a_module_verifies_images_without_importing_cryptography(caterpillar: CompiledProgram, tmp_path: Path) -> None:
    """Packed here (signing needs cryptography), examined in a fresh process as a module
    does it: OK, TAMPERED and WRONG_KEY; cryptography (OpenSSL) never imported there, PyNaCl
    only once an image is verified."""
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
        "from dh2rt.signed_image import examine, parse, read_public_key, verify\n"
        f"d = Path({str(tmp_path)!r})\n"
        "image, tampered = (d / 'image').read_bytes(), (d / 'tampered').read_bytes()\n"
        "key, other = read_public_key(d / 'key'), read_public_key(d / 'other')\n"
        "print('nacl' in sys.modules)\n"
        "print(examine(image, [key]).verdict, examine(tampered, [key]).verdict, examine(image, [other]).verdict,"
        " verify(parse(image), [other, key]))\n"
        "print('cryptography' in sys.modules, sorted(m for m in sys.modules if m.startswith('cryptography')))\n"
        "print('nacl' in sys.modules, '_ssl' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["False", "ok tampered wrong key ok", "False []", "True False"]
