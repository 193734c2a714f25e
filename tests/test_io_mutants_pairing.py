"""io.pairing tests that kill mutants the behaviour tests let through (docs/mutation.md): pair names
at the edge of the `.urdf` suffix, two recorded digests, and the exact pairing comment with and
without an XML declaration."""

from __future__ import annotations

from pathlib import Path

import pytest

from m3t1r.errors import ModelFileError
from m3t1r.io.pairing import paired_closures_path, recorded_closures_sha256, sha256_bytes, with_closures_sha256

A = "a" * 64
B = "b" * 64
COMMENT = (b"<!-- m3t1r pair: closures sha256 " + A.encode()
           + b" (this URDF loads only with the closures file of that content; models/README.md) -->\n")


@pytest.mark.parametrize(("urdf", "closures"), [
    ("m.urdf", "m.closures.yaml"),
    ("dir/M.URDF", "dir/M.closures.yaml"),
    (".urdf", ".urdf.closures.yaml"),  # nothing before the suffix: not a suffix
    ("machine.xml", "machine.xml.closures.yaml"),
    ("urdf", "urdf.closures.yaml"),
])
def test_pair_names(urdf, closures):
    assert paired_closures_path(urdf) == Path(closures)


def test_two_different_recorded_digests_are_refused():
    urdf = with_closures_sha256(b"<robot/>", A) + b"<!-- m3t1r pair: closures sha256 " + B.encode() + b" -->\n"
    with pytest.raises(ModelFileError) as caught:
        recorded_closures_sha256(urdf)
    assert caught.value.path == "URDF"
    assert str(caught.value) == "URDF: records two different closures sha256 digests"
    assert recorded_closures_sha256(with_closures_sha256(b"<robot/>", A) + COMMENT) == A


def test_comment_without_a_declaration_goes_first():
    assert with_closures_sha256(b"<robot/>\n", A) == COMMENT + b"<robot/>\n"


def test_comment_after_a_declaration_with_and_without_its_newline():
    assert with_closures_sha256(b'<?xml version="1.0"?>\n<robot/>', A) == b'<?xml version="1.0"?>\n' + COMMENT + b"<robot/>"
    assert with_closures_sha256(b'<?xml version="1.0"?><robot/>', A) == (
        b'<?xml version="1.0"?>\n' + COMMENT + b"<robot/>")


def test_comment_is_replaced_and_removed():
    paired = with_closures_sha256(b"<robot/>", A)
    assert with_closures_sha256(paired, B) == COMMENT.replace(A.encode(), B.encode()) + b"<robot/>"
    assert with_closures_sha256(paired, None) == b"<robot/>"
    assert recorded_closures_sha256(b"<robot/>") is None


@pytest.mark.parametrize("digest", ["A" * 64, "a" * 63, sha256_bytes(b"x")[:-1] + "g"])
def test_a_digest_must_be_64_lowercase_hex(digest):
    with pytest.raises(ValueError, match=rf"^not a sha256 hex digest: '{digest}'$"):
        with_closures_sha256(b"<robot/>", digest)
