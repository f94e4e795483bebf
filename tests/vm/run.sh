#!/usr/bin/env bash
# tests/vm/run.sh FLAVOR OUTDIR GUEST_SCRIPT [HOST_FILE...]
#
# Boots the Debian 6.1 kernel prepared by prepare.sh (FLAVOR = std | rt)
# under QEMU (TCG, -icount: guest time is virtual and deterministic-ish,
# independent of host load) with a fresh busybox initramfs containing:
#   /init              tests/vm/guest/init (mounts, insmods, runs the test)
#   /lib/vmtest.sh     helpers (make_sim_chip, start/stop_gpio_trace, ...)
#   /test.sh           GUEST_SCRIPT, run with busybox sh in /out
#   /bin/<name>        each HOST_FILE (static binaries: the guest has no libc)
# Everything the script writes to /out ends up in OUTDIR, next to
# OUTDIR/console.log (serial console), OUTDIR/dmesg.log (guest kernel log)
# OUTDIR/serial1.bin and OUTDIR/serial2.bin (what the guest wrote to its
# second and third serial ports, ttyS1 and ttyS2).
# The exit status is the one of /test.sh; 124 on timeout, 125 when the VM
# produced no result (panic, setup failure), 2 on usage errors.
#
# Environment:
#   PPM_VM_CACHE    cache directory (see prepare.sh)
#   PPM_VM_TIMEOUT  wall-clock limit in seconds for the VM (default 300)
#   PPM_VM_MEM      guest memory (default 512M)
#   PPM_VM_APPEND   extra kernel command line
#   PPM_VM_BOOT_OPTS  replaces the default boot-speed options (see below)
#   PPM_VM_QUIET=1  do not echo the console to stdout (shown on failure)
#   PPM_VM_*        all PPM_VM_* / VMTEST_* variables are also exported
#                   into the guest (e.g. VMTEST_TRACE_BUF_KB).
set -euo pipefail

die() { echo "run.sh: error: $1" >&2; exit "${2:-2}"; }
log() { echo "run.sh: $*" >&2; }

[ $# -ge 3 ] || die "usage: $0 std|rt OUTDIR GUEST_SCRIPT [HOST_FILE...]"
FLAVOR=$1 OUTDIR=$2 SCRIPT=$3; shift 3
case "$FLAVOR" in std|rt) ;; *) die "FLAVOR must be std or rt" ;; esac
[ -f "$SCRIPT" ] || die "guest script $SCRIPT not found"
for f in "$@"; do [ -f "$f" ] || die "host file $f not found"; done

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
CACHE=${PPM_VM_CACHE:-$ROOT/target/vm/cache}
TIMEOUT=${PPM_VM_TIMEOUT:-300}

for t in qemu-system-x86_64 cpio busybox timeout tar; do
    command -v "$t" >/dev/null || die "$t not found; run tests/vm/prepare.sh $FLAVOR for the list of host packages"
done

# prepare.sh is cheap when warm (<1 s), but skip it when its result exists.
if [ ! -f "$CACHE/$FLAVOR.env" ]; then
    "$HERE/prepare.sh" "$FLAVOR" >/dev/null
fi
# shellcheck disable=SC1090,SC1091
. "$CACHE/$FLAVOR.env"
if [ -z "${KERNEL:-}" ] || [ ! -f "$KERNEL" ] || [ ! -f "$MODDIR/load.order" ]; then
    die "cache for $FLAVOR is incomplete; rerun tests/vm/prepare.sh $FLAVOR"
fi

mkdir -p "$OUTDIR"
OUTDIR=$(cd "$OUTDIR" && pwd)
# Start from a clean OUTDIR so that stale files cannot pass for results, but
# only empty directories that an earlier run.sh made (marker file), never a
# directory of the user's by mistake.
if [ -n "$(ls -A "$OUTDIR")" ]; then
    [ -f "$OUTDIR/.vmtest-outdir" ] ||
        die "OUTDIR $OUTDIR is not empty and was not made by run.sh; refusing to clear it"
    find "$OUTDIR" -mindepth 1 -delete
fi
touch "$OUTDIR/.vmtest-outdir"

STAGE=$(mktemp -d "${TMPDIR:-/tmp}/ppm-vm.XXXXXX")
# shellcheck disable=SC2317 # called through the trap
cleanup() { rm -rf "$STAGE"; }
trap cleanup EXIT

# ------------------------------------------------------------ initramfs
R=$STAGE/root
mkdir -p "$R"/{bin,sbin,usr/bin,usr/sbin,lib/modules,etc,proc,sys,dev,tmp,out,root}
BUSYBOX=$(command -v busybox)
cp "$BUSYBOX" "$R/bin/busybox"
# Applet links made on the host: cheaper than `busybox --install` at boot.
for applet in $("$BUSYBOX" --list); do
    [ "$applet" = busybox ] || ln -s busybox "$R/bin/$applet"
done
cp "$HERE/guest/init" "$R/init"
cp "$HERE/guest/vmtest.sh" "$R/lib/vmtest.sh"
cp "$SCRIPT" "$R/test.sh"
cp "$MODDIR"/*.ko "$MODDIR/load.order" "$R/lib/modules/"
chmod 755 "$R/init" "$R/test.sh"
for f in "$@"; do
    if command -v readelf >/dev/null &&
       [[ $(readelf -l "$f" 2>/dev/null) == *'Requesting program interpreter'* ]]; then
        log "warning: $f is dynamically linked; the guest has no libc (build it static)"
    fi
    # rm first: a name that is also a busybox applet is a symlink to busybox,
    # and cp would overwrite busybox itself through it.
    rm -f "$R/bin/$(basename "$f")"
    cp "$f" "$R/bin/"
    chmod 755 "$R/bin/$(basename "$f")"
    # Without debug info: the initramfs is unpacked into guest RAM, and the
    # release profile's line tables make each binary 3 to 5 times larger
    # (five of them outgrew 512M of guest RAM: "Initramfs unpacking failed").
    if command -v strip >/dev/null; then
        strip --strip-debug "$R/bin/$(basename "$f")"
    fi
done
# Pass PPM_VM_* / VMTEST_* settings to the guest, single-quoted for ash.
for name in ${!PPM_VM_@} ${!VMTEST_@}; do
    val=${!name}
    printf "export %s='%s'\n" "$name" "${val//\'/\'\\\'\'}"
done > "$R/etc/vmtest.env"

INITRD=$STAGE/initrd.cpio
# Uncompressed newc cpio: building and unpacking it is faster than gzip
# under TCG, and its size only costs guest RAM briefly.
(cd "$R" && find . -mindepth 1 | LC_ALL=C sort | cpio -o -H newc -R 0:0 --quiet) > "$INITRD"

# ---------------------------------------------------------------- boot
# Results come back as a tar written by the guest to a raw virtio disk:
# reliable for binary data of any size, unlike the serial console, which
# also carries kernel messages. A sparse file costs nothing.
DISK=$STAGE/result.img
truncate -s "${PPM_VM_RESULT_MB:-512}M" "$DISK"

# Boot-time savings under TCG (measured: ~8 s -> ~2.5 s per boot together
# with the PVH vmlinux): skip the crypto self-tests (~0.7 s guest time) and
# the local APIC timer calibration loop (~3 s wall; HPET becomes the
# clockevent device instead), no CPU vulnerability mitigations (speed only;
# this VM runs nothing untrusted), trust the (virtual, icount-driven) TSC.
# Set PPM_VM_BOOT_OPTS to replace them, e.g. PPM_VM_BOOT_OPTS= for none.
BOOT_OPTS=${PPM_VM_BOOT_OPTS-cryptomgr.notests noapictimer mitigations=off tsc=reliable}

CONSOLE=$OUTDIR/console.log
# shellcheck disable=SC2054 # commas belong to qemu option values
QEMU=(qemu-system-x86_64
    -accel tcg
    # One vCPU and instruction counting: guest time advances 1 ns per
    # instruction and jumps over idle periods (sleep=off), so timing seen in
    # the guest does not depend on host load and sleeps cost no wall time.
    -icount shift=0,sleep=off
    -smp 1 -m "${PPM_VM_MEM:-512M}"
    -nographic -no-reboot -nic none
    -kernel "$KERNEL" -initrd "$INITRD"
    -append "console=ttyS0 panic=-1 quiet $BOOT_OPTS ${PPM_VM_APPEND:-}"
    -drive "file=$DISK,format=raw,if=virtio,cache=unsafe"
    # The console on ttyS0 (with the monitor, as -nographic has it), and a
    # second serial port, the guest's ttyS1, whose bytes land in
    # OUTDIR/serial1.bin: the SBUS output's capture.
    -serial mon:stdio
    -serial "file:$OUTDIR/serial1.bin"
    # A third, the guest's ttyS2, into OUTDIR/serial2.bin: the CRSF
    # output's capture.
    -serial "file:$OUTDIR/serial2.bin"
)
log "booting $KREL ($FLAVOR), timeout ${TIMEOUT}s, console: $CONSOLE"
start_ms=$(date +%s%3N)
set +e
if [ "${PPM_VM_QUIET:-0}" = 1 ]; then
    timeout -k 10 "$TIMEOUT" "${QEMU[@]}" </dev/null 2>&1 | tr -d '\r' > "$CONSOLE"
else
    timeout -k 10 "$TIMEOUT" "${QEMU[@]}" </dev/null 2>&1 | stdbuf -o0 tr -d '\r' | tee "$CONSOLE"
fi
qemu_rc=${PIPESTATUS[0]}
set -e
elapsed_ms=$(( $(date +%s%3N) - start_ms ))
elapsed=$((elapsed_ms / 1000)).$(printf '%03d' $((elapsed_ms % 1000)))
log "VM finished after ${elapsed}s (qemu status $qemu_rc)"

show_console_on_failure() {
    if [ "${PPM_VM_QUIET:-0}" = 1 ]; then
        echo "---- last lines of $CONSOLE ----" >&2
        tail -n 60 "$CONSOLE" >&2
        echo "----" >&2
    fi
}

if [ "$qemu_rc" = 124 ] || [ "$qemu_rc" = 137 ]; then
    show_console_on_failure
    die "VM timed out after ${TIMEOUT}s (PPM_VM_TIMEOUT); see $CONSOLE" 124
fi

# --------------------------------------------------------------- results
RES=$STAGE/result
mkdir -p "$RES"
if ! tar -xf "$DISK" -C "$RES" 2>"$STAGE/tar.err" || [ ! -f "$RES/rc" ]; then
    show_console_on_failure
    if grep -q 'Kernel panic' "$CONSOLE"; then
        die "guest kernel panicked: $(grep -m1 'Kernel panic' "$CONSOLE"); see $CONSOLE" 125
    fi
    die "VM gave no result (qemu status $qemu_rc; $(head -c 200 "$STAGE/tar.err")); see $CONSOLE" 125
fi
[ -f "$RES/dmesg.log" ] && mv "$RES/dmesg.log" "$OUTDIR/dmesg.log"
if [ -d "$RES/out" ]; then
    (cd "$RES/out" && find . -mindepth 1 -maxdepth 1 -exec mv -t "$OUTDIR" {} +)
fi
rc=$(cat "$RES/rc")
case "$rc" in ''|*[!0-9]*) die "bad exit status '$rc' from guest" 125 ;; esac
if [ "$rc" != 0 ]; then
    show_console_on_failure
    log "guest test $SCRIPT FAILED with status $rc ($FLAVOR); output in $OUTDIR"
else
    log "guest test $SCRIPT passed ($FLAVOR); output in $OUTDIR"
fi
exit "$rc"
