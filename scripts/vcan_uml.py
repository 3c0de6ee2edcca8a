"""Running a command inside user-mode Linux beside a real ``vcan0``: the guest's init script,
the boot, the host-side timeout, the command's output and exit status. Part of
``vcan_pytest.py``."""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vcan_host import CAN_MODULES, REPO_ROOT, UML_MODULES_ROOT, VCAN_CHANNEL, find_uml_binary, log

EXIT_TIMEOUT = 124
EXIT_UML_CANNOT_BOOT = 125
"""run_uml: the guest died at boot with UML_FP_PANIC (UML cannot run on this host's CPU)."""
UML_FP_PANIC = "ptrace set fp regs failed"

INIT_TEMPLATE_FILE = Path(__file__).with_name("uml_init.sh")
"""The guest's init script; ``@NAME@`` placeholders are filled in by :func:`write_init_script`."""
GUEST_OWN_MOUNTS = ("/proc", "/sys", "/dev")
"""Mounted anew inside the guest (uml_init.sh); everything else is the host's, through hostfs."""


def guest_hidden_mount(path: Path) -> str | None:
    """The guest's own mount that hides host ``path`` from the guest, or None if it sees it."""
    for mount in GUEST_OWN_MOUNTS:
        if path == Path(mount) or Path(mount) in path.parents:
            return mount
    return None


def write_init_script(
    workdir: Path,
    cmd: list[str],
    env: dict[str, str],
    inner_timeout: int | None,
    modules_root: Path = UML_MODULES_ROOT,
    cwd: Path = REPO_ROOT,
) -> Path:
    """Fill in the guest's init script in ``workdir``: it runs ``cmd`` in ``cwd`` (a host path,
    which the guest sees at the same place) with exactly ``env``."""
    timeout_prefix = ""
    if inner_timeout is not None and shutil.which("timeout"):
        # Lets the guest record output and status before the host-side timeout fires.
        timeout_prefix = f"timeout -k 10 {inner_timeout} "
    values = {
        "WORKDIR": shlex.quote(str(workdir)),
        "MODULES": " ".join(CAN_MODULES),
        "MODROOT": shlex.quote(str(modules_root)),
        "CHANNEL": VCAN_CHANNEL,
        "CWD": shlex.quote(str(cwd)),
        "TIMEOUT_PREFIX": timeout_prefix,
        "ENV": " ".join(shlex.quote(f"{k}={v}") for k, v in sorted(env.items())),
        "CMD": shlex.join(cmd),
    }
    script = re.sub(r"@([A-Z_]+)@", lambda m: values[m.group(1)], INIT_TEMPLATE_FILE.read_text())
    init = workdir / "init.sh"
    init.write_text(script)
    init.chmod(0o700)
    return init


def uml_memory_tmpdir(mem_mib: int, fallback: Path) -> str:
    """Where linux.uml creates its (sparse, unlinked) guest-RAM file: /dev/shm if big enough."""
    try:
        st = os.statvfs("/dev/shm")
        if st.f_bavail * st.f_frsize >= mem_mib * 1024 * 1024:
            return "/dev/shm"
    except OSError:
        pass
    return str(fallback)


def kill_group(proc: subprocess.Popen[bytes]) -> None:
    """Terminate the UML process group we started (UML runs guest processes as host children)."""

    def signal_group(sig: signal.Signals) -> bool:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            return False
        return True

    if proc.poll() is None and signal_group(signal.SIGTERM):
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5.0)
    # Also reaps any helper process the UML kernel process left behind in its group.
    signal_group(signal.SIGKILL)
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        log(f"warning: linux.uml (pid {proc.pid}) did not exit after SIGKILL")


class _Tail:
    """Copy bytes appended to a file to our stdout (hostfs writes through to the host file)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.pos = 0

    def pump(self) -> None:
        try:
            with self.path.open("rb") as fh:
                fh.seek(self.pos)
                data = fh.read()
        except FileNotFoundError:
            return
        if data:
            self.pos += len(data)
            sys.stdout.buffer.write(data)
            sys.stdout.buffer.flush()


def print_file_tail(path: Path, lines: int = 40) -> None:
    try:
        text = path.read_text(errors="replace").splitlines()
    except FileNotFoundError:
        log(f"({path.name} missing)")
        return
    for line in text[-lines:]:
        print(f"  | {line}", file=sys.stderr)


def run_uml(
    cmd: list[str],
    env: dict[str, str],
    timeout: float,
    mem_mib: int,
    keep: bool,
    kernel: tuple[str, Path] | None = None,
    cwd: Path = REPO_ROOT,
) -> int:
    """Boot UML (``kernel``: its binary and module root; default the distribution's) to run
    ``cmd`` in ``cwd`` beside a real vcan0; the command's exit status, or this script's own
    codes."""
    uml, modules_root = kernel or (find_uml_binary(), UML_MODULES_ROOT)
    if uml is None:
        log("linux.uml not found")
        return 1
    base = Path(tempfile.gettempdir())
    if str(base.resolve()).startswith(("/dev/shm", "/proc", "/sys", "/dev")):
        base = Path("/tmp")  # those are remounted inside the guest; /tmp is the host's /tmp
    workdir = Path(tempfile.mkdtemp(prefix="vcan-uml-", dir=base))
    # The guest-side timeout fires first so the guest can still record output and status.
    reserve = min(timeout / 2, max(15.0, timeout * 0.05))
    inner_timeout = max(int(timeout - reserve), 1)
    init = write_init_script(workdir, cmd, env, inner_timeout, modules_root, cwd)
    boot_log = workdir / "boot.log"
    uml_cmd = [
        uml,
        f"mem={mem_mib}M",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        f"init={init}",
        "con=null",
        "con0=fd:0,fd:1",
        # UML keeps its pid/mconsole files under uml_dir (default ~/.uml; without HOME it crashes).
        f"uml_dir={workdir}",
    ]
    uml_env = dict(os.environ)
    uml_env["HOME"] = os.environ.get("HOME") or str(workdir)
    uml_env["TMPDIR"] = uml_memory_tmpdir(mem_mib, workdir)
    log(f"booting user-mode Linux ({uml}, mem={mem_mib}M) to get a real {VCAN_CHANNEL}")
    log(f"guest runs: {shlex.join(cmd)}  (cwd {cwd}, work dir {workdir})")
    tail = _Tail(workdir / "output.log")
    start = time.monotonic()
    ready_at: float | None = None
    timed_out = False
    interrupted = False
    with boot_log.open("wb") as boot_fh:
        proc = subprocess.Popen(
            uml_cmd,
            stdin=subprocess.DEVNULL,
            stdout=boot_fh,
            stderr=subprocess.STDOUT,
            env=uml_env,
            cwd=workdir,
            start_new_session=True,  # own process group: killable as a whole
        )
        previous_term = signal.getsignal(signal.SIGTERM)

        def on_term(signum: int, frame: object) -> None:
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, on_term)
        try:
            while proc.poll() is None:
                if ready_at is None and (workdir / "ready").exists():
                    ready_at = time.monotonic()
                    log(f"guest ready ({VCAN_CHANNEL} up) after {ready_at - start:.1f} s")
                tail.pump()
                if time.monotonic() - start > timeout:
                    timed_out = True
                    break
                time.sleep(0.2)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            kill_group(proc)
            signal.signal(signal.SIGTERM, previous_term)
    tail.pump()
    if interrupted:
        log("interrupted; stopped user-mode Linux")
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
        return 130
    elapsed = time.monotonic() - start
    rc_file = workdir / "rc"
    failed_setup = workdir / "setup_failed"
    result: int
    if failed_setup.exists():
        log(f"guest could not set up {VCAN_CHANNEL}: {failed_setup.read_text().strip()}")
        print_file_tail(workdir / "setup.log")
        print_file_tail(boot_log, 15)
        result = 1
    elif rc_file.exists():
        result = int(rc_file.read_text().strip() or "1")
        log(f"guest command exited with {result}; boot + run took {elapsed:.1f} s")
        if result == EXIT_TIMEOUT and inner_timeout and elapsed >= inner_timeout:
            log(f"the command hit the guest-side timeout ({inner_timeout} s)")
    elif timed_out:
        log(f"timeout: user-mode Linux still running after {timeout:.0f} s; killed it")
        print_file_tail(workdir / "setup.log", 10)
        print_file_tail(boot_log, 15)
        result = EXIT_TIMEOUT
    else:
        log(
            f"user-mode Linux exited ({proc.returncode}) after {elapsed:.1f} s "
            "without recording the command's status; end of boot log:"
        )
        print_file_tail(workdir / "setup.log", 20)
        print_file_tail(boot_log, 30)
        result = 1
        with contextlib.suppress(OSError):
            if UML_FP_PANIC in boot_log.read_text(errors="replace"):
                result = EXIT_UML_CANNOT_BOOT
    if keep:
        log(f"kept work dir {workdir} (init.sh, boot.log, setup.log, output.log, rc)")
    else:
        shutil.rmtree(workdir, ignore_errors=True)
    return result
