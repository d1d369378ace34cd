"""Signed program images: the binary layout, signatures, refusals, key files and the CLI."""

from __future__ import annotations

import hashlib
import stat
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt import ed25519
from dh2rt import signed_image as si
from dh2rt.cli import main
from dh2rt.compiler import compile_file, load_image
from dh2rt.errors import ImageError, KeyFileError, SignedImageError
from dh2rt.program import CompiledProgram
from dh2rt.signed_image import Verdict
from dh2rt.wire.frame import program_digest
from tests.dh2rt.forgery import WEAK_KEYS, forge, openssl_accepts

#: The target of issue 11: the caterpillar's signed image, signature included.
CATERPILLAR_LIMIT = 512
SEED = bytes(range(32))

#: A signed image of format 1 made once (program "tiny", version 5, key SEED). Every later
#: dh2rt must read it: header layout, preset dictionary and signature are frozen.
GOLDEN = bytes.fromhex(
    "44483253010000000574b850835c4f56475aa75463474c000002100000004a732150169294b2504c36a9ad452d"
    "4871263e250f25a4f4178be4fb92ccbc4a2562cb5d02514d7c5cc62239ac5687847844682c82644f6a471da17c"
    "87120106b5b5b558b204deeaa91600d292d346cd316aa886d9fdad2d81af66c7e70a5e46562be185a5c8ead140"
    "8c15e924db2140ac2b89a300d4caaf9c1a89b950e1babb47279a60b0a0105d4dd60e"
)
GOLDEN_PROGRAM = (
    b'DH2IMG1\n{"":"Program","consts":[{"":"Const","name":"ClockCycle","value":{"":"Num","value":4}}],'
    b'"hormones":[{"":"HormoneDecl","name":"H","params":[]}],"name":"tiny","natives":[],"options":[],'
    b'"receptors":[{"":"Receptor","actions":[{"":"Emit","hormone":{"":"HormoneTerm","args":[],"name":"H"},'
    b'"target":{"":"ViaConnector","name":"back"}}],"name":"r","pattern":{"":"And","left":{"":"TypeIs",'
    b'"negate":false,"types":["T1"]},"right":{"":"TimerIs","op":"==","value":{"":"Num","value":0}}},'
    b'"status":"active"}],"sensors":[],"variables":[]}'
)


@pytest.fixture(scope="module")
def key() -> bytes:
    return si.new_private_key()


@pytest.fixture(scope="module")
def signed_caterpillar(caterpillar: CompiledProgram, key: bytes) -> bytes:
    return si.pack(caterpillar.image, 7, key)


# ---------------------------------------------------------------- the format


def test_round_trip_gives_the_compiled_program(
    caterpillar: CompiledProgram, key: bytes, signed_caterpillar: bytes
) -> None:
    image = si.parse(signed_caterpillar)
    assert (image.format_version, image.version, image.size) == (1, 7, len(signed_caterpillar))
    assert image.digest == program_digest(caterpillar.image)  # what the Hello carries
    assert image.key_id == hashlib.sha256(si.public_key(key)).digest()[:8]
    assert image.program_length == len(caterpillar.image)
    assert si.verify(image, [si.public_key(key)]) is Verdict.OK
    loaded = load_image(image.program())
    assert loaded.image == caterpillar.image and loaded.hash == caterpillar.hash


@pytest.mark.parametrize("name", ["caterpillar", "legs_to_snake", "locomotion"])
def test_every_example_round_trips(examples: Path, key: bytes, name: str) -> None:
    cp = compile_file(str(examples / f"{name}.dh2"))
    exam = si.examine(si.pack(cp.image, 1, key), [si.public_key(key)])
    assert exam.verdict is Verdict.OK and exam.program == cp.image


def test_the_signed_caterpillar_fits_in_512_bytes(
    caterpillar: CompiledProgram, signed_caterpillar: bytes, capsys: pytest.CaptureFixture[str]
) -> None:
    with capsys.disabled():
        sys.stdout.write(
            f"\ncaterpillar: signed image {len(signed_caterpillar)} bytes "
            f"(signature {si.SIGNATURE_BYTES}), JSON image {len(caterpillar.image)} bytes\n"
        )
    assert len(signed_caterpillar) <= CATERPILLAR_LIMIT


def test_the_layout_is_the_documented_one(caterpillar: CompiledProgram, key: bytes, signed_caterpillar: bytes) -> None:
    magic, fmt, version, digest, kid, length, body = struct.unpack_from(">4sBI6s8sII", signed_caterpillar)
    assert (magic, fmt, version, length) == (b"DH2S", 1, 7, len(caterpillar.image))
    assert digest == program_digest(caterpillar.image) and kid == si.key_id(si.public_key(key))
    assert len(signed_caterpillar) == 31 + body + 64


def test_an_image_signed_once_still_reads() -> None:
    image = si.parse(GOLDEN)
    assert (image.version, image.key_id) == (5, si.key_id(si.public_key(SEED)))
    assert si.verify(image, [si.public_key(SEED)]) is Verdict.OK
    assert image.program() == GOLDEN_PROGRAM


# ---------------------------------------------------------------- refusals


def _region(offset: int, size: int) -> str:
    for name, start, length in si.FIELDS:
        if start <= offset < start + length:
            return name
    return "signature" if offset >= size - si.SIGNATURE_BYTES else "body"


#: What flipping one bit in each part of an image makes of it.
TAMPER_VERDICTS = {
    "magic": {Verdict.MALFORMED},
    "format version": {Verdict.MALFORMED},
    "program version": {Verdict.TAMPERED},
    "program digest": {Verdict.TAMPERED},
    "key id": {Verdict.WRONG_KEY},
    # a length still in range parses: then the signature no longer matches
    "program length": {Verdict.MALFORMED, Verdict.TAMPERED},
    "body length": {Verdict.MALFORMED},
    "body": {Verdict.TAMPERED},
    "signature": {Verdict.TAMPERED},
}


def test_every_one_bit_change_is_refused(signed_caterpillar: bytes, key: bytes) -> None:
    trust = [si.public_key(key)]
    seen: dict[str, set[Verdict]] = {}
    for offset in range(len(signed_caterpillar)):
        for bit in range(8):
            tampered = bytearray(signed_caterpillar)
            tampered[offset] ^= 1 << bit
            exam = si.examine(bytes(tampered), trust)
            region = _region(offset, len(signed_caterpillar))
            assert exam.verdict in TAMPER_VERDICTS[region], (offset, bit, region, exam.reason)
            assert exam.program is None
            seen.setdefault(region, set()).add(exam.verdict)
    assert set(seen) == set(TAMPER_VERDICTS)


def test_a_wrong_key_is_refused(caterpillar: CompiledProgram, key: bytes) -> None:
    other = si.new_private_key()
    data = si.pack(caterpillar.image, 1, other)
    exam = si.examine(data, [si.public_key(key)])
    assert exam.verdict is Verdict.WRONG_KEY and si.key_id(si.public_key(other)).hex() in exam.reason
    assert si.examine(data, []).verdict is Verdict.WRONG_KEY
    assert si.examine(data, [si.public_key(key), si.public_key(other)]).verdict is Verdict.OK


def test_a_key_id_that_names_a_trusted_key_does_not_lend_its_trust(caterpillar: CompiledProgram, key: bytes) -> None:
    """An image signed by another key but carrying the trusted key's id: the signature fails."""
    forged = bytearray(si.pack(caterpillar.image, 1, si.new_private_key()))
    forged[15:23] = si.key_id(si.public_key(key))
    assert si.examine(bytes(forged), [si.public_key(key)]).verdict is Verdict.TAMPERED


def test_todays_image_reads_as_unsigned_version_0(caterpillar: CompiledProgram, key: bytes) -> None:
    image = si.parse(caterpillar.image)
    assert (image.signed, image.version, image.format_version, image.key_id) == (False, 0, 0, None)
    assert image.digest == program_digest(caterpillar.image)
    exam = si.examine(caterpillar.image, [si.public_key(key)])
    assert exam.verdict is Verdict.UNSIGNED and exam.program == caterpillar.image


@pytest.mark.parametrize("cut", range(0, 200, 3))
def test_a_cut_image_names_the_field_and_offset(signed_caterpillar: bytes, cut: int) -> None:
    with pytest.raises(SignedImageError, match="offset") as info:
        si.parse(signed_caterpillar[:cut] if cut else b"DH")
    region = _region(cut, len(signed_caterpillar)) if cut else "magic"
    assert f"cut short in the {region}" in str(info.value)


def test_a_cut_signature_and_trailing_bytes_are_named(signed_caterpillar: bytes) -> None:
    with pytest.raises(SignedImageError, match="cut short in the signature"):
        si.parse(signed_caterpillar[:-1])
    with pytest.raises(SignedImageError, match="trailing bytes after the signature"):
        si.parse(signed_caterpillar + b"\0")


@pytest.mark.parametrize("garbage", [b"", b"hello, world", b"\x7fELF\x02\x01\x01", b"DH2X" + bytes(100)])
def test_garbage_is_no_image(garbage: bytes) -> None:
    with pytest.raises(SignedImageError, match="not a DH2 program image"):
        si.parse(garbage)
    assert si.examine(garbage, []).verdict is Verdict.MALFORMED


def test_foreign_format_and_absurd_lengths_are_named(signed_caterpillar: bytes) -> None:
    other_format = signed_caterpillar[:4] + b"\x02" + signed_caterpillar[5:]
    with pytest.raises(SignedImageError, match="format version 2 at offset 4"):
        si.parse(other_format)
    no_program = signed_caterpillar[:23] + bytes(4) + signed_caterpillar[27:]
    with pytest.raises(SignedImageError, match="program length 0 at offset 23"):
        si.parse(no_program)


def _sign_raw(header_fields: tuple[int, bytes, int, int], body: bytes, key: bytes) -> bytes:
    """A correctly signed image around any body: what a careless signer could make."""
    version, digest, length, _ = header_fields
    signed_part = si.HEADER.pack(si.MAGIC, 1, version, digest, si.key_id(si.public_key(key)), length, len(body)) + body
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return signed_part + Ed25519PrivateKey.from_private_bytes(key).sign(signed_part)


def test_a_signed_body_that_is_no_program_is_malformed(caterpillar: CompiledProgram, key: bytes) -> None:
    trust = [si.public_key(key)]
    digest = program_digest(caterpillar.image)
    garbage = _sign_raw((1, digest, 100, 0), b"\xff" * 40, key)
    assert si.examine(garbage, trust).verdict is Verdict.MALFORMED
    body = si.parse(si.pack(caterpillar.image, 1, key)).body
    short = _sign_raw((1, digest, 100, 0), body, key)  # inflates to more than it says: stopped
    exam = si.examine(short, trust)
    assert exam.verdict is Verdict.MALFORMED and "program length" in exam.reason
    wrong_digest = _sign_raw((1, bytes(6), len(caterpillar.image), 0), body, key)
    exam = si.examine(wrong_digest, trust)
    assert exam.verdict is Verdict.MALFORMED and "program digest" in exam.reason


def test_pack_refuses_what_is_no_signed_program(caterpillar: CompiledProgram, key: bytes) -> None:
    with pytest.raises(ImageError, match=r"outside 0\.\.4294967295"):
        si.pack(caterpillar.image, 2**32, key)
    with pytest.raises(ImageError, match="not a DH2 program image"):
        si.pack(b"#!/bin/sh\n", 1, key)
    with pytest.raises(KeyFileError):
        si.pack(caterpillar.image, 1, b"short")


def test_cryptography_is_not_imported_by_importing_these() -> None:
    """Only signing and key generation import it (verifying is dh2rt.ed25519: test_ed25519);
    PyNaCl only verifying, not reading a raw key and checking that it is not weak."""
    code = (
        "import sys\nimport dh2rt.cli, dh2rt.signed_image, firmware.flash.slots, firmware.module_toml\n"
        "dh2rt.signed_image.decode_public_key(bytes.fromhex("
        "'d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a'))\n"
        "print('cryptography' in sys.modules, 'nacl' in sys.modules)\n"
    )
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=60)
    assert (out.returncode, out.stdout.strip()) == (0, "False False"), out.stderr


# ---------------------------------------------------------------- keys


def test_keys_read_as_pem_or_raw(key: bytes) -> None:
    public = si.public_key(key)
    assert si.decode_private_key(si.private_key_pem(key)) == key == si.decode_private_key(key)
    assert si.decode_public_key(si.public_key_pem(public)) == public == si.decode_public_key(public)


def test_key_files_of_the_wrong_kind_are_named(key: bytes) -> None:
    with pytest.raises(KeyFileError, match="holds a public key"):
        si.decode_private_key(si.public_key_pem(si.public_key(key)))
    with pytest.raises(KeyFileError, match="holds a private key"):
        si.decode_public_key(si.private_key_pem(key))
    with pytest.raises(KeyFileError, match="7 bytes"):
        si.decode_public_key(b"not key")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey

    x25519 = X25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    with pytest.raises(KeyFileError, match="not an Ed25519 key"):
        si.decode_private_key(x25519)
    with pytest.raises(KeyFileError, match="not a readable PEM"):
        si.decode_private_key(b"-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n")


@pytest.mark.parametrize("weak", list(WEAK_KEYS.values()), ids=list(WEAK_KEYS))
def test_a_weak_public_key_is_refused_when_read(weak: bytes, tmp_path: Path) -> None:
    """Every encoding of a point of small order, raw or PEM: anyone can forge its signatures."""
    raw, pem = tmp_path / "raw.pub", tmp_path / "pem.pub"
    raw.write_bytes(weak)
    pem.write_bytes(si.public_key_pem(weak))
    for path in (raw, pem):
        with pytest.raises(KeyFileError, match=rf"^{path}: refused: a weak Ed25519 public key, a point of small order"):
            si.read_public_key(path)
    with pytest.raises(KeyFileError, match="small order"):
        si.check_public_key(weak)


def test_an_all_zero_key_file_is_refused_naming_it(tmp_path: Path) -> None:
    zeros = tmp_path / "zeros.pub"
    zeros.write_bytes(bytes(32))
    with pytest.raises(KeyFileError) as caught:
        si.read_public_key(zeros)
    assert str(caught.value).startswith(f"{zeros}: refused: a weak Ed25519 public key")
    assert "all zeros" in str(caught.value) and "forge" in str(caught.value)


def test_keys_that_are_no_point_or_not_canonical_are_refused_when_read(key: bytes) -> None:
    public = si.public_key(key)
    off_curve = next(k for i in range(256) if ed25519.weakness(k := public[:-1] + bytes([i])) is not None)
    with pytest.raises(KeyFileError, match="no point of the curve"):
        si.decode_public_key(off_curve)
    with pytest.raises(KeyFileError, match="not a canonical encoding"):
        si.decode_public_key((2**255 - 19 + 2).to_bytes(32, "little"))  # y = 2 + p


@pytest.mark.parametrize("weak", list(WEAK_KEYS.values()), ids=list(WEAK_KEYS))
def test_an_image_forged_for_a_weak_key_is_refused(caterpillar: CompiledProgram, weak: bytes) -> None:
    """R of small order, S = 0, no private key: OpenSSL accepts the signature (as dh2rt's own
    verifier did before issue 27); dh2rt refuses it even when the weak key is trusted."""
    forged = forge(caterpillar.image, weak)
    signed = si.parse(forged)
    assert openssl_accepts(weak, forged[-64:], signed.signed_part)
    assert si.verify(signed, [weak]) is Verdict.TAMPERED
    exam = si.examine(forged, [weak])
    assert exam.verdict is Verdict.TAMPERED and "a weak key" in exam.reason and exam.program is None


def test_a_key_pair_file_is_private_and_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "key"
    kid = si.write_key_pair(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert si.key_id(si.read_public_key(tmp_path / "key.pub")) == kid
    assert si.public_key(si.read_private_key(path)) == si.read_public_key(tmp_path / "key.pub")
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        si.write_key_pair(path)
    assert path.read_bytes() == before


# ---------------------------------------------------------------- the command line


@pytest.fixture
def keyfile(tmp_path: Path) -> Path:
    path = tmp_path / "keys" / "signer"
    path.parent.mkdir()  # a folder outside the current one is not made unasked
    assert main(["keys", "new", "-o", str(path)]) == 0
    return path


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def test_keys_new_writes_a_private_and_a_public_key(keyfile: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert stat.S_IMODE(keyfile.stat().st_mode) == 0o600
    public = si.read_public_key(keyfile.with_name("signer.pub"))
    code, _, err = _run(["keys", "new", "-o", str(keyfile)], capsys)
    assert code == 2 and "exists" in err and "never overwritten" in err
    assert si.public_key(si.read_private_key(keyfile)) == public


def test_keys_new_prints_the_key_id(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(["keys", "new", "-o", str(tmp_path / "k")], capsys)
    kid = si.key_id(si.read_public_key(tmp_path / "k.pub")).hex()
    assert code == 0 and f"key id {kid}" in out


def test_image_sign_and_inspect(
    examples: Path, keyfile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_path = tmp_path / "cat.simg"
    caterpillar = str(examples / "caterpillar.dh2")
    code, out, _ = _run(["image", caterpillar, "--sign", str(keyfile), "--version", "9", "-o", str(out_path)], capsys)
    assert code == 0 and "signed: version 9" in out
    assert len(out_path.read_bytes()) <= CATERPILLAR_LIMIT
    pub = str(keyfile.with_name("signer.pub"))
    code, out, _ = _run(["image", "--inspect", str(out_path), "--trust", pub], capsys)
    kid = si.key_id(si.read_public_key(Path(pub))).hex()
    assert code == 0
    assert "program version  9" in out and f"key id           {kid}" in out and "verification     ok" in out
    code, out, _ = _run(["image", "--inspect", str(out_path)], capsys)
    assert code == 0 and "not checked" in out


def test_inspect_exit_codes(examples: Path, keyfile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    signed = tmp_path / "cat.simg"
    plain = tmp_path / "cat.img"
    caterpillar = str(examples / "caterpillar.dh2")
    assert main(["image", caterpillar, "--sign", str(keyfile), "--version", "1", "-o", str(signed)]) == 0
    assert main(["image", caterpillar, "-o", str(plain)]) == 0
    assert main(["keys", "new", "-o", str(tmp_path / "other")]) == 0
    tampered = tmp_path / "tampered.simg"
    data = bytearray(signed.read_bytes())
    data[100] ^= 0x10
    tampered.write_bytes(bytes(data))
    capsys.readouterr()
    pub, other = str(keyfile.with_name("signer.pub")), str(tmp_path / "other.pub")
    cases = [
        ([str(signed), "--trust", other], 1, "wrong key"),
        ([str(tampered), "--trust", pub], 1, "tampered"),
        ([str(plain), "--trust", pub], 1, "unsigned"),
        ([str(plain)], 0, "unsigned program image"),
        ([str(signed), "--trust", str(keyfile)], 2, "holds a private key"),
        ([pub], 2, "not a DH2 program image"),
        ([str(tmp_path / "missing.simg")], 2, "No such file"),
    ]
    for args, expected, text in cases:
        code, out, err = _run(["image", "--inspect", *args], capsys)
        assert (code, text in out + err) == (expected, True), (args, out, err)


@pytest.mark.parametrize("weak", list(WEAK_KEYS.values()), ids=list(WEAK_KEYS))
def test_inspect_refuses_a_weak_trusted_key_naming_it(
    weak: bytes, caterpillar: CompiledProgram, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``image --inspect FORGED --trust WEAK.pub`` said "verification ok" before issue 27."""
    forged, pub = tmp_path / "forged.simg", tmp_path / "weak.pub"
    forged.write_bytes(forge(caterpillar.image, weak))
    pub.write_bytes(weak)
    code, out, err = _run(["image", "--inspect", str(forged), "--trust", str(pub)], capsys)
    assert code == 2 and f"{pub}: refused: a weak Ed25519 public key" in err, err
    assert "verification" not in out


def test_image_options_that_do_not_go_together(
    examples: Path, keyfile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    caterpillar = str(examples / "caterpillar.dh2")
    out = str(tmp_path / "x.simg")
    pub = str(keyfile.with_name("signer.pub"))
    cases = [
        (["image", caterpillar, "--sign", str(keyfile), "-o", out], "go together"),
        (["image", caterpillar, "--version", "3", "-o", out], "go together"),
        (["image", caterpillar, "--sign", pub, "--version", "3", "-o", out], "holds a public key"),
        (["image", caterpillar, "--sign", str(keyfile), "--version", "-1", "-o", out], "outside 0..4294967295"),
        (["image", caterpillar, "--sign", str(tmp_path / "nokey"), "--version", "1", "-o", out], "No such file"),
        (["image", caterpillar], "give PROGRAM and -o FILE"),
        (["image", "--inspect", out, caterpillar], "takes no PROGRAM"),
        (["image", caterpillar, "-o", out, "--trust", pub], "--trust goes with --inspect"),
    ]
    for args, text in cases:
        code, _, err = _run(args, capsys)
        assert code == 2 and text in err, (args, err)
    assert not Path(out).exists()


def test_unsigned_image_output_is_unchanged(examples: Path, tmp_path: Path, caterpillar: CompiledProgram) -> None:
    out = tmp_path / "program.img"
    assert main(["image", str(examples / "caterpillar.dh2"), "-o", str(out)]) == 0
    assert out.read_bytes() == caterpillar.image
