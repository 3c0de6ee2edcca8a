"""``scripts/uml_newer.py``: which packages Debian's index names, which index hash the signed
release gives, and which installed UML a cache holds (no network, no boot)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

INDEX = """Package: libc6
Version: 2.43-7
Filename: pool/main/g/glibc/libc6_2.43-7_amd64.deb
SHA256: aaaa
Description: GNU C Library
 a continuation line: Package: not-this

Package: user-mode-linux
Version: 7.2um1
Filename: pool/main/u/user-mode-linux/user-mode-linux_7.2um1_amd64.deb
SHA256: bbbb

Package: user-mode-linux
Version: 6.0um1
Filename: pool/main/u/user-mode-linux/old.deb
SHA256: cccc
"""

RELEASE = """Origin: Debian
Suite: unstable
MD5Sum:
 d70654e4ff73403c5076a564041f1484 10824484 main/binary-amd64/Packages.xz
SHA256:
 1111 100 main/binary-arm64/Packages.xz
 2222 10824484 main/binary-amd64/Packages.xz
"""


def _script():
    spec = importlib.util.spec_from_file_location("uml_newer", ROOT / "scripts/uml_newer.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("uml_newer", module)  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def test_the_index_gives_each_package_its_first_stanza():
    found = _script().parse_index(INDEX)
    assert found["user-mode-linux"]["Version"] == "7.2um1"
    assert found["user-mode-linux"]["SHA256"] == "bbbb"
    assert found["libc6"]["Filename"] == "pool/main/g/glibc/libc6_2.43-7_amd64.deb"


def test_an_index_without_a_package_is_an_error():
    m = _script()
    with pytest.raises(m.UmlFetchError, match="no user-mode-linux"):
        m.parse_index(INDEX.split("\n\n")[0])


def test_the_index_hash_comes_from_the_release_sha256_section():
    m = _script()
    assert m.signed_index_sha256(RELEASE) == "2222"
    with pytest.raises(m.UmlFetchError, match="no SHA256"):
        m.signed_index_sha256(RELEASE.split("SHA256:")[0])


def test_only_a_completed_install_is_used(tmp_path):
    m = _script()
    assert m.installed(tmp_path / "missing") is None
    partial = tmp_path / "7.2um1"
    (partial / "modules").mkdir(parents=True)
    (partial / "linux.uml").write_bytes(b"\x7fELF")
    assert m.installed(tmp_path) is None  # interrupted before patchelf: fetched again
    (partial / "complete").write_text("7.2um1\n")
    got = m.installed(tmp_path)
    assert got.binary == partial / "linux.uml" and got.modules_root == partial / "modules"
    assert got.version == "7.2um1"
