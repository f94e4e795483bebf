#!/usr/bin/env bash
# tests/vm/arm64/prepare.sh [--check]   (--check: only whether the host
#                                        has the tools named below)
#
# Prepares a Debian bookworm arm64 system that boots with systemd as PID 1
# under qemu-system-aarch64 -M virt (software emulation), for the package's
# whole-system test (tests/tests/vm_arm64.rs, tests/vm/arm64/run.sh):
#   - a root file system made with mmdebstrap (systemd, udev, apt, networkd
#     for QEMU's user network, Debian's standard and PREEMPT_RT arm64
#     kernels with small initramfs images that mount a virtio-mmio disk and
#     a 9p share), and a test-runner unit that runs the share's guest.sh
#     after boot and powers off;
#   - gpio-sim.ko and irq_sim.ko built out of tree for both kernels (Debian
#     builds neither), cross-compiled with aarch64-linux-gnu- against the
#     kernels' own headers and the host's linux-kbuild-6.1, in
#     /opt/ppm-vmtest/KREL/ of the image;
#   - the image as an ext4 file (run.sh boots a copy-on-write overlay of it).
#
# Cached in $PPM_VM_CACHE/arm64 (default target/vm/cache/arm64), keyed on
# this script: a warm run takes a second. A cold one about 8 minutes.
# Result: arm64/current.env (IMAGE, and KREL_std, KREL_rt with their
# vmlinuz and initrd paths).
#
# Host packages (Debian 12): mmdebstrap arch-test qemu-user-static
# qemu-system-arm qemu-utils e2fsprogs gcc-aarch64-linux-gnu, and
# binfmt_misc mounted (this script mounts it and registers qemu-aarch64
# when it can). The kernel sources are GPL-2.0: fetched here, kept only in
# the cache, never committed.
set -euo pipefail

die() { echo "arm64/prepare.sh: error: $*" >&2; exit 1; }
log() { echo "arm64/prepare.sh: [${SECONDS}s] $*" >&2; }

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../../.." && pwd)
CACHE=${PPM_VM_CACHE:-$ROOT/target/vm/cache}
mkdir -p "$CACHE/arm64"
CACHE=$(cd "$CACHE" && pwd)
OUT=$CACHE/arm64
exec 9>"$OUT/.prepare.lock"
flock 9

# TOOL:PACKAGE; every missing one is named, with the package to install.
need=()
for pair in mmdebstrap:mmdebstrap arch-test:arch-test qemu-aarch64-static:qemu-user-static \
            qemu-system-aarch64:qemu-system-arm qemu-img:qemu-utils mkfs.ext4:e2fsprogs \
            aarch64-linux-gnu-gcc:gcc-aarch64-linux-gnu apt-get:apt dpkg-deb:dpkg make:make; do
    command -v "${pair%%:*}" >/dev/null || {
        echo "arm64/prepare.sh: ${pair%%:*} not found (package ${pair#*:})" >&2
        need+=("${pair#*:}")
    }
done
[ ${#need[@]} -eq 0 ] || die "missing host tools; install them with:
    apt-get update && apt-get install -y --no-install-recommends ${need[*]}
(qemu-system-arm and qemu-utils must be of one version: a newer qemu-utils breaks the release's qemu-system-common)"
# --check: only whether the host has every tool (CI asks before its tests).
[ "${1:-}" != --check ] || { log "every host tool is there"; exit 0; }

# What goes into the image; the key covers it and this script.
PACKAGES="systemd,systemd-sysv,udev,kmod,dbus,procps,iproute2,initramfs-tools,linux-image-arm64,linux-image-rt-arm64"
KEY=$(cat "$0" "$HERE/guest-runner.service" | sha256sum | cut -c1-16)
if [ -f "$OUT/current.env" ] && grep -qx "KEY=$KEY" "$OUT/current.env"; then
    log "cached: $(grep '^IMAGE=' "$OUT/current.env")"
    exit 0
fi

# foreign architecture maintainer scripts run through qemu-aarch64-static
if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
    mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc 2>/dev/null ||
        die "binfmt_misc is not mounted and cannot be: mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc"
fi
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
    /lib/systemd/systemd-binfmt /usr/lib/binfmt.d/qemu-aarch64.conf 2>/dev/null ||
        update-binfmts --enable qemu-aarch64 2>/dev/null ||
        die "cannot register qemu-aarch64 with binfmt_misc"
fi

WORK=$(mktemp -d "${TMPDIR:-/tmp}/ppm-arm64-prepare.XXXXXX")
# mmdebstrap mounts /proc, /sys and /dev into the root file system while it
# works, and an interrupted run leaves them: unmount before removing, and
# never follow a mount out of the work directory.
# shellcheck disable=SC2317 # called through the trap
cleanup() {
    awk -v w="$WORK/" 'index($2, w) == 1 { print $2 }' /proc/mounts | sort -r |
        while read -r m; do umount -l "$m" || true; done
    rm -rf --one-file-system "$WORK"
}
trap cleanup EXIT
RFS=$WORK/rootfs

log "mmdebstrap bookworm arm64 (a few minutes)"
# Before the kernels are installed: small initramfs images with what the
# root disk and the share need. After: the network, the share, the runner.
mmdebstrap --arch=arm64 --variant=apt --include="$PACKAGES" \
    --essential-hook='mkdir -p "$1/etc/initramfs-tools/conf.d" && echo MODULES=list > "$1/etc/initramfs-tools/conf.d/ppm-vmtest" && printf "virtio_mmio\nvirtio_blk\next4\n9p\n9pnet_virtio\n" >> "$1/etc/initramfs-tools/modules"' \
    --customize-hook="cp '$HERE/guest-runner.service' \"\$1/etc/systemd/system/ppm-vmtest.service\"" \
    --customize-hook='chroot "$1" systemctl enable ppm-vmtest.service systemd-networkd.service' \
    --customize-hook='printf "[Match]\nName=e*\n[Network]\nDHCP=yes\n" > "$1/etc/systemd/network/10-vm.network"' \
    --customize-hook='printf "/dev/vda / ext4 rw,noatime 0 1\nout /mnt/out 9p trans=virtio,version=9p2000.L,msize=262144,nofail 0 0\n" > "$1/etc/fstab" && mkdir -p "$1/mnt/out"' \
    --customize-hook='echo ppm-vm > "$1/etc/hostname"' \
    --customize-hook='chroot "$1" sh -c "mkdir -p /var/cache/ppm-headers && cd /var/cache/ppm-headers && for k in \$(ls /boot | sed -n s/^vmlinuz-//p); do apt-get download -q linux-headers-\$k \$(apt-cache depends linux-headers-\$k | sed -n \"s/^ *Depends: \\(linux-headers-[^ ]*common[^ ]*\\).*/\\1/p\"); done"' \
    --customize-hook='echo 7070707070707070707070707070aa01 > "$1/etc/machine-id"' \
    --customize-hook='chroot "$1" systemctl mask systemd-firstboot.service apt-daily.timer apt-daily-upgrade.timer' \
    bookworm "$RFS" \
    "deb http://deb.debian.org/debian bookworm main" \
    "deb http://deb.debian.org/debian bookworm-updates main" \
    "deb http://deb.debian.org/debian-security bookworm-security main" \
    > "$WORK/mmdebstrap.log" 2>&1 || { tail -40 "$WORK/mmdebstrap.log" >&2; die "mmdebstrap failed"; }

# The two kernels and their ABI, from what was installed.
declare -A KREL
for f in "$RFS"/boot/vmlinuz-*; do
    k=${f##*/vmlinuz-}
    case "$k" in *-rt-arm64) KREL[rt]=$k ;; *-arm64) KREL[std]=$k ;; esac
done
[ -n "${KREL[std]:-}" ] && [ -n "${KREL[rt]:-}" ] || die "kernels missing in /boot: $(ls "$RFS/boot")"
DEBVER=$(dpkg-query --admindir="$RFS/var/lib/dpkg" -W -f='${Version}' "linux-image-${KREL[std]}")
log "kernels ${KREL[std]} and ${KREL[rt]} (Debian $DEBVER)"

# gpio-sim and irq_sim for both, with the host's kbuild tools. The sources
# come from linux-source-6.1 (140 MB of xz), unpacked once per Debian
# version next to the x86 kernels' (tests/vm/prepare.sh keeps the same
# files there).
SRC_FILES="drivers/gpio/gpio-sim.c drivers/gpio/gpiolib.h kernel/irq/irq_sim.c"
SRC=$CACHE/src-$DEBVER
have_src() { for f in $SRC_FILES; do [ -f "$SRC/$f" ] || return 1; done; }
# The host's (amd64) packages at the kernels' Debian version; when the
# archive has only another revision of the same upstream version for amd64
# (a rebuild: 6.1.192-3 beside arm64's 6.1.192-2), that one: modpost and the
# gpio-sim sources are the upstream version's.
host_version() { # PACKAGE
    local versions up
    versions=$(apt-cache madison "$1" 2>/dev/null | awk '{print $3}')
    if grep -qxF "$DEBVER" <<<"$versions"; then
        echo "$DEBVER"
        return
    fi
    up=${DEBVER%-*}
    grep -F "$up-" <<<"$versions" | grep "^${up//./\.}-" | sort -V | tail -n 1
}
KBUILD=$(host_version linux-kbuild-6.1)
[ -n "$KBUILD" ] || die "no linux-kbuild-6.1 of upstream ${DEBVER%-*} in apt for the kernels $DEBVER (run apt-get update)"
[ "$KBUILD" = "$DEBVER" ] || log "linux-kbuild-6.1 $DEBVER is not in apt for this host: $KBUILD, of the same upstream version"
PKGS="linux-kbuild-6.1=$KBUILD"
if ! have_src; then
    SOURCE=$(host_version linux-source-6.1)
    [ -n "$SOURCE" ] || die "no linux-source-6.1 of upstream ${DEBVER%-*} in apt (run apt-get update)"
    PKGS="$PKGS linux-source-6.1=$SOURCE"
fi
mkdir -p "$WORK/debs" "$WORK/host"
# shellcheck disable=SC2086 # one package per word
( cd "$WORK/debs" && apt-get download -q $PKGS ) > "$WORK/download.log" 2>&1 ||
    { cat "$WORK/download.log" >&2; die "apt-get download of $PKGS failed (apt-get update?)"; }
dpkg-deb -x "$WORK"/debs/linux-kbuild-6.1_*.deb "$WORK/host"
if ! have_src; then
    mkdir -p "$WORK/src"
    # shellcheck disable=SC2046 # one path per word
    dpkg-deb --fsys-tarfile "$(echo "$WORK"/debs/linux-source-6.1_*.deb)" |
        tar -xOf - ./usr/src/linux-source-6.1.tar.xz |
        tar -xJf - -C "$WORK/src" --strip-components=1 \
            $(for f in $SRC_FILES; do echo "linux-source-6.1/$f"; done)
    SRC=$WORK/src
fi
# The kernels' headers, downloaded (not installed: a smaller image and
# dpkg database) by the chroot's apt above and unpacked next to the host's
# kbuild, so that their scripts link resolves to the host's (amd64) tools.
ls "$RFS"/var/cache/ppm-headers/linux-headers-*.deb >/dev/null 2>&1 || die "the headers were not downloaded"
for deb in "$RFS"/var/cache/ppm-headers/*.deb; do dpkg-deb -x "$deb" "$WORK/host"; done
rm -rf "$RFS/var/cache/ppm-headers"
for flavor in std rt; do
    k=${KREL[$flavor]}
    HDR=$WORK/host/usr/src/linux-headers-$k
    sed -i "s#^include /usr/src/#include $WORK/host/usr/src/#" "$HDR/Makefile"
    B=$WORK/build-$flavor
    mkdir -p "$B"
    for f in $SRC_FILES; do cp "$SRC/$f" "$B/"; done
    # As tests/vm/prepare.sh: irq_to_desc is not exported; a license tag.
    sed -i 's/handle_simple_irq(irq_to_desc(irqnum));/generic_handle_irq(irqnum);/' "$B/irq_sim.c"
    grep -q 'irq_to_desc' "$B/irq_sim.c" && die "could not patch irq_sim.c"
    printf '\n#include <linux/module.h>\nMODULE_LICENSE("GPL");\n' >> "$B/irq_sim.c"
    echo 'obj-m := irq_sim.o gpio-sim.o' > "$B/Kbuild"
    make -C "$HDR" M="$B" ARCH=arm64 CROSS_COMPILE=aarch64-linux-gnu- -j2 modules \
        > "$WORK/build-$flavor.log" 2>&1 || { tail -30 "$WORK/build-$flavor.log" >&2; die "gpio-sim build for $k failed"; }
    mkdir -p "$RFS/opt/ppm-vmtest/$k"
    cp "$B/irq_sim.ko" "$B/gpio-sim.ko" "$RFS/opt/ppm-vmtest/$k/"
done
log "built gpio-sim for both kernels"

IMG=$OUT/rootfs-$KEY.ext4
rm -f "$OUT"/rootfs-*.ext4
truncate -s 3G "$IMG.tmp"
mkfs.ext4 -q -L root -d "$RFS" "$IMG.tmp" || die "mkfs.ext4 -d failed"
mv "$IMG.tmp" "$IMG"
for flavor in std rt; do
    k=${KREL[$flavor]}
    cp "$RFS/boot/vmlinuz-$k" "$OUT/vmlinuz-$k"
    cp "$RFS/boot/initrd.img-$k" "$OUT/initrd.img-$k"
done
{
    echo "KEY=$KEY"
    echo "IMAGE=$IMG"
    echo "DEBVER=$DEBVER"
    for flavor in std rt; do
        echo "KREL_$flavor=${KREL[$flavor]}"
        echo "VMLINUZ_$flavor=$OUT/vmlinuz-${KREL[$flavor]}"
        echo "INITRD_$flavor=$OUT/initrd.img-${KREL[$flavor]}"
    done
} > "$OUT/current.env"
log "image $IMG"
