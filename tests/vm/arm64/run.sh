#!/usr/bin/env bash
# tests/vm/arm64/run.sh std|rt SHARE HOSTPORT
#
# Boots the Debian bookworm arm64 system that prepare.sh made, with systemd
# as PID 1, under qemu-system-aarch64 -M virt (software emulation, four
# vCPUs as a Pi 4 or 5 has), on Debian's standard (std) or PREEMPT_RT (rt)
# arm64 kernel. The root disk is a copy-on-write overlay of the cached
# image: every boot starts from the same system.
# Guest time counts instructions (-icount shift=0: 1 ns each), so that
# the host's other work cannot make the guest's ppmd late: a vCPU held up
# on the host is held up in guest time too. With sleep=on an idle guest's
# clock follows the host's, so that commands the host sends 20 ms apart
# reach the guest about 20 ms apart. The four vCPUs then share one host
# thread, taking turns: ppmd can still be held up while another vCPU runs.
#   - SHARE is the guest's /mnt/out (virtio 9p): put guest.sh and what it
#     needs there; the guest's test-runner unit runs it once the system is
#     up, writes SHARE/guest.log and SHARE/status (its exit status), and
#     powers the machine off.
#   - UDP to 127.0.0.1:HOSTPORT on the host reaches the guest's port 5005
#     through QEMU's user network (10.0.2.15 in the guest).
#   - The serial console goes to SHARE/console.log.
# Exit status: the guest's; 124 on timeout, 125 when the guest wrote none.
#
# Environment: PPM_VM_CACHE (see prepare.sh), PPM_VM_TIMEOUT (wall-clock
# limit in seconds, default 900).
set -euo pipefail

die() { echo "arm64/run.sh: error: $1" >&2; exit "${2:-2}"; }
log() { echo "arm64/run.sh: $*" >&2; }

[ $# -eq 3 ] || die "usage: $0 std|rt SHARE HOSTPORT"
FLAVOR=$1 SHARE=$2 PORT=$3
case "$FLAVOR" in std|rt) ;; *) die "FLAVOR must be std or rt" ;; esac
[ -d "$SHARE" ] || die "share $SHARE is not a directory"
[ -f "$SHARE/guest.sh" ] || die "no guest.sh in $SHARE"
SHARE=$(cd "$SHARE" && pwd)

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
"$HERE/prepare.sh"
ROOT=$(cd "$HERE/../../.." && pwd)
CACHE=${PPM_VM_CACHE:-$ROOT/target/vm/cache}
# shellcheck disable=SC1091
. "$CACHE/arm64/current.env"
KREL=KREL_$FLAVOR VMLINUZ=VMLINUZ_$FLAVOR INITRD=INITRD_$FLAVOR
KREL=${!KREL} VMLINUZ=${!VMLINUZ} INITRD=${!INITRD}

STAGE=$(mktemp -d "${TMPDIR:-/tmp}/ppm-arm64-vm.XXXXXX")
trap 'rm -rf "$STAGE"' EXIT
qemu-img create -q -f qcow2 -b "$IMAGE" -F raw "$STAGE/root.qcow2"
rm -f "$SHARE/status" "$SHARE/console.log"

TIMEOUT=${PPM_VM_TIMEOUT:-900}
# shellcheck disable=SC2054 # commas belong to qemu option values
QEMU=(qemu-system-aarch64
    -M virt -cpu cortex-a72 -smp 4 -m 1024
    -icount shift=0,sleep=on
    -name ppm-arm64,debug-threads=on
    -nographic -no-reboot
    -kernel "$VMLINUZ" -initrd "$INITRD"
    -append "root=/dev/vda rw console=ttyAMA0 panic=-1 quiet systemd.show_status=0"
    -drive "file=$STAGE/root.qcow2,format=qcow2,if=none,id=root,cache=unsafe"
    -device virtio-blk-device,drive=root
    -fsdev "local,id=out,path=$SHARE,security_model=none"
    -device virtio-9p-device,fsdev=out,mount_tag=out
    -netdev "user,id=net,hostfwd=udp:127.0.0.1:$PORT-:5005"
    -device virtio-net-device,netdev=net
    -serial "file:$SHARE/console.log"
    -monitor none
)
log "booting $KREL ($FLAVOR), timeout ${TIMEOUT}s, console $SHARE/console.log"
start=$SECONDS
timeout -k 10 "$TIMEOUT" "${QEMU[@]}" </dev/null >"$STAGE/qemu.log" 2>&1 &
vm=$!
set +e
wait "$vm"
qemu_rc=$?
set -e
log "VM finished after $((SECONDS - start)) s (qemu status $qemu_rc)"
if [ "$qemu_rc" = 124 ] || [ "$qemu_rc" = 137 ]; then
    tail -n 40 "$SHARE/console.log" >&2 || true
    die "VM timed out after ${TIMEOUT}s (PPM_VM_TIMEOUT)" 124
fi
if [ ! -s "$SHARE/status" ]; then
    cat "$STAGE/qemu.log" >&2
    tail -n 40 "$SHARE/console.log" >&2 || true
    die "the guest wrote no status (qemu status $qemu_rc)" 125
fi
exit "$(cat "$SHARE/status")"
