#!/bin/sh
# Template read by scripts/vcan_pytest.py, which fills in the upper-case placeholders between at
# signs: init (PID 1) of a user-mode Linux guest.
# Sets up SocketCAN vcan0, runs one command, records its status and powers off.
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
W=@WORKDIR@
SETUP_LOG="$W/setup.log"
OUT="$W/output.log"

finish() {
    sync
    echo o > /proc/sysrq-trigger 2>/dev/null
    sleep 2
    poweroff -f 2>/dev/null
    halt -f -p 2>/dev/null
    # Last resort: PID 1 exiting panics the kernel, which makes linux.uml abort.
    exit 1
}

fail_setup() {
    echo "vcan setup failed: $*" >> "$SETUP_LOG"
    echo "$*" > "$W/setup_failed"
    finish
}

exec >> "$SETUP_LOG" 2>&1
set -x
mount -t proc proc /proc || fail_setup "mount /proc"
mount -t sysfs sysfs /sys || fail_setup "mount /sys"
[ -e /dev/null ] || mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/shm /dev/pts
mount -t tmpfs -o mode=1777,size=50% tmpfs /dev/shm || fail_setup "mount tmpfs on /dev/shm"
mount -t devpts -o gid=5,mode=620,ptmxmode=666 devpts /dev/pts || true
[ -e /dev/fd ] || ln -s /proc/self/fd /dev/fd
hostname vcan-uml 2>/dev/null || true
ip link set lo up || fail_setup "ip link set lo up"
KVER=$(uname -r)
MODDIR=@MODROOT@/$KVER
[ -d "$MODDIR" ] || fail_setup "no module directory $MODDIR for UML kernel $KVER"
for m in @MODULES@; do
    # Known locations first (shell builtins only: every process spawn costs ~0.1 s in UML).
    f=
    for c in "$MODDIR"/kernel/net/can/"$m".ko* "$MODDIR"/kernel/drivers/net/can/"$m".ko* \
             "$MODDIR"/kernel/drivers/net/can/dev/"$m".ko*; do
        [ -f "$c" ] && f=$c && break
    done
    [ -n "$f" ] || f=$(find "$MODDIR" -name "$m.ko" -o -name "$m.ko.*" | head -n 1)
    [ -n "$f" ] || fail_setup "module $m not found under $MODDIR"
    insmod "$f" || fail_setup "insmod $f"
done
ip link add dev @CHANNEL@ type vcan || fail_setup "ip link add dev @CHANNEL@ type vcan"
ip link set @CHANNEL@ mtu 72 || fail_setup "ip link set @CHANNEL@ mtu 72 (CAN FD)"
ip link set up @CHANNEL@ || fail_setup "ip link set up @CHANNEL@"
ip -details link show @CHANNEL@
set +x
echo ready > "$W/ready"

cd @CWD@ || fail_setup "cd @CWD@"
@TIMEOUT_PREFIX@env -i @ENV@ @CMD@ < /dev/null > "$OUT" 2>&1
rc=$?
echo "$rc" > "$W/rc.tmp" && mv "$W/rc.tmp" "$W/rc"
finish
