#!/usr/bin/env bash
# tests/vm/prepare.sh FLAVOR      (FLAVOR = std | rt)
# tests/vm/prepare.sh --check     (only: are the host tools below there?)
#
# Prepares everything needed to boot a real Debian 6.1 kernel under QEMU
# with the gpio-sim driver, without installing any kernel on the host:
#   - picks a kernel ABI (6.1.0-NN) for which image + headers of BOTH
#     flavours and the matching linux-source-6.1 / linux-kbuild-6.1 exist
#     in the configured apt repositories (override: PPM_VM_KABI=NN);
#   - `apt-get download`s the packages and unpacks them with `dpkg-deb -x`
#     into a scratch directory (tmpfs when possible), deleted at the end;
#   - builds gpio-sim.ko, irq_sim.ko and spi-gpio.ko out of tree from
#     linux-source-6.1 (Debian builds none of them: CONFIG_GPIO_SIM,
#     CONFIG_IRQ_SIM and CONFIG_SPI_GPIO are unset), and our board module
#     ppm_spi_board.ko (tests/vm/ppm_spi_board.c: spi-gpio on gpio-sim lines);
#   - keeps only vmlinuz (+ the uncompressed vmlinux, which boots ~5 s
#     faster under TCG), the kernel config and the few modules the guest
#     needs (configfs, virtio-blk for the result disk, irq_sim, gpio-sim,
#     spi-bitbang, spi-gpio, plus their dependencies; ppm_spi_board is kept
#     but not loaded at boot, the SPI test insmods it with its parameters):
#     ~40 MB per flavour.
#
# Result (cached, idempotent): $CACHE/<kernel release>/{vmlinuz,vmlinux,config,modules/}
# and $CACHE/FLAVOR.env, which run.sh sources. CACHE defaults to
# <workspace>/target/vm/cache; override with PPM_VM_CACHE (CI: point it at a
# directory outside the fresh clone to keep it warm). A warm run takes about
# a second (apt-cache look-ups only) and needs no network. A cold run takes
# ~20 s for the first flavour, ~10 s for the second (sources are shared).
#
# The kernel sources are GPL-2.0: they are fetched here at test time and live
# only in the cache; never commit them.
#
# Host packages needed (Debian 12; install them yourself or in CI, this script
# never installs anything):
#   apt-get install -y --no-install-recommends \
#     qemu-system-x86 busybox-static cpio xz-utils make gcc-12 binutils \
#     libelf1 libssl3
# (apt and dpkg are part of every Debian system. `apt-get update` must have
# run once so that apt-cache / apt-get download know the kernel packages.)
set -euo pipefail

die() { echo "prepare.sh: error: $*" >&2; exit 1; }
log() { echo "prepare.sh: [${SECONDS}s] $*" >&2; }

[ $# -eq 1 ] || die "usage: $0 std|rt|--check"
FLAVOR=$1
case "$FLAVOR" in
    --check) ;;
    std) VARIANT=amd64;    COMMON_SUFFIX= ;;
    rt)  VARIANT=rt-amd64; COMMON_SUFFIX=-rt ;;
    *) die "FLAVOR must be 'std' or 'rt', got '$FLAVOR'" ;;
esac

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
CACHE=${PPM_VM_CACHE:-$ROOT/target/vm/cache}
mkdir -p "$CACHE"
CACHE=$(cd "$CACHE" && pwd)
# One prepare at a time per cache: the two flavours share the unpacked
# kernel source, and the tests prepare both at once.
exec 9>"$CACHE/.prepare.lock"
flock 9

# Modules (from the image package) that the guest needs besides our two.
# configfs is =m in Debian's config (gpio-sim is configured through it);
# virtio_blk/virtio_pci carry the result disk that run.sh reads back.
# Dependencies are resolved from each module's .modinfo "depends=" field.
# spi_bitbang (=m) is what spi-gpio (built here) uses; spidev is =y.
WANTED_IMAGE_MODULES="configfs virtio_pci virtio_blk spi_bitbang"
# Bump when the build recipe changes so that stale caches are rebuilt.
RECIPE_VERSION=4
# The GPL sources taken from linux-source-6.1 (shared by both flavours).
SRC_FILES="drivers/gpio/gpio-sim.c drivers/gpio/gpiolib.h kernel/irq/irq_sim.c drivers/spi/spi-gpio.c drivers/spi/spi-bitbang-txrx.h"

# ---------------------------------------------------------------- host tools
check_tools() {
    local missing_pkgs=() tool pkg
    # tool:package pairs
    for pair in qemu-system-x86_64:qemu-system-x86 cpio:cpio \
                xz:xz-utils make:make gcc-12:gcc-12 objcopy:binutils \
                readelf:binutils dpkg-deb:dpkg apt-get:apt apt-cache:apt; do
        tool=${pair%%:*}; pkg=${pair#*:}
        command -v "$tool" >/dev/null 2>&1 || missing_pkgs+=("$pkg")
    done
    # The guest needs a *static* busybox (Debian's 'busybox' package is
    # dynamic and conflicts with busybox-static).
    # (Outputs are captured before grep: with pipefail, `cmd | grep -q` fails
    # at random when grep exits early and cmd dies of SIGPIPE.)
    if ! BUSYBOX=$(command -v busybox) || ! command -v readelf >/dev/null ||
       [[ $(readelf -l "$BUSYBOX" 2>/dev/null) == *'Requesting program interpreter'* ]]; then
        missing_pkgs+=(busybox-static)
    fi
    # Runtime libraries of linux-kbuild-6.1's prebuilt modpost/genksyms.
    local libs
    libs=$(ldconfig -p 2>/dev/null || true)
    for lib in libelf.so.1:libelf1 libssl.so.3:libssl3; do
        [[ $libs == *"${lib%%:*}"* ]] || missing_pkgs+=("${lib#*:}")
    done
    if [ ${#missing_pkgs[@]} -gt 0 ]; then
        die "missing host tools; install them with:
    apt-get update && apt-get install -y --no-install-recommends $(printf '%s\n' "${missing_pkgs[@]}" | sort -u | tr '\n' ' ')"
    fi
}

# ---------------------------------------------------------- kernel selection
# Prints "NN VERSION" for the newest ABI whose 8 packages all exist at the
# same Debian version (e.g. "56 6.1.192-2"). Old ABIs vanish from the archive
# when Debian publishes updates, so we select dynamically instead of pinning.
# All "package version" pairs apt knows for the candidate ABIs, fetched with
# a single apt-cache call (one call per package makes a warm run take seconds).
MADISON=
load_madison() { # NN...
    local nn pkgs=(linux-kbuild-6.1 linux-source-6.1)
    # shellcheck disable=SC2207 # package names have no spaces or globs
    for nn in "$@"; do pkgs+=($(abi_packages "$nn")); done
    MADISON=$(apt-cache madison "${pkgs[@]}" 2>/dev/null |
        awk -F'|' '{gsub(/ /,"",$1); gsub(/ /,"",$2); print $1" "$2}' | sort -u)
}
pkg_versions() { awk -v p="$1" '$1==p {print $2}' <<<"$MADISON"; }
abi_packages() { # NN -> the six per-ABI package names
    echo "linux-image-6.1.0-$1-amd64-unsigned linux-image-6.1.0-$1-rt-amd64-unsigned" \
         "linux-headers-6.1.0-$1-amd64 linux-headers-6.1.0-$1-rt-amd64" \
         "linux-headers-6.1.0-$1-common linux-headers-6.1.0-$1-common-rt"
}
abi_complete() { # NN VERSION
    local p
    for p in $(abi_packages "$1") linux-kbuild-6.1 linux-source-6.1; do
        grep -qxF "$p $2" <<<"$MADISON" || return 1
    done
}
select_abi() {
    local nn ver candidates
    if [ -n "${PPM_VM_KABI:-}" ]; then
        candidates=$PPM_VM_KABI
    else
        candidates=$(apt-cache pkgnames linux-image-6.1.0- 2>/dev/null |
            sed -n 's/^linux-image-6\.1\.0-\([0-9]\+\)-amd64-unsigned$/\1/p' | sort -rn)
    fi
    [ -n "$candidates" ] || return 1
    # shellcheck disable=SC2086 # one ABI number per word
    load_madison $candidates
    for nn in $candidates; do
        for ver in $(pkg_versions "linux-image-6.1.0-$nn-amd64-unsigned"); do
            abi_complete "$nn" "$ver" && { echo "$nn $ver"; return 0; }
        done
    done
    return 1
}

# ------------------------------------------------------------------ helpers
# modinfo without kmod: read the .modinfo section of a .ko.
modinfo_field() { # FILE FIELD
    objcopy -O binary -j .modinfo "$1" /dev/stdout 2>/dev/null | tr '\0' '\n' |
        sed -n "s/^$2=//p" | sed -n 1p
}
norm() { echo "${1//-/_}"; }

# Copies module NAME (and, first, its dependencies) from the unpacked image
# tree into $MODOUT, appending to $MODOUT/load.order in load order.
declare -A MODPATH=() MODSEEN=()
add_module() {
    local name dep file
    name=$(norm "$1")
    [ -z "${MODSEEN[$name]:-}" ] || return 0
    MODSEEN[$name]=1
    if grep -q "/$name.ko\$" "$BUILTIN_LIST" 2>/dev/null ||
       grep -q "/$(echo "$name" | tr '_' '-').ko\$" "$BUILTIN_LIST" 2>/dev/null; then
        log "  $name is built into the kernel"
        return 0
    fi
    file=${MODPATH[$name]:-}
    [ -n "$file" ] || die "module $name not found in the image package"
    for dep in $(modinfo_field "$file" depends | tr ',' ' '); do
        add_module "$dep"
    done
    cp "$file" "$MODOUT/$name.ko"
    echo "$name" >> "$MODOUT/load.order"
}

# ---------------------------------------------------------------------- main
check_tools
# --check: only whether the host has every tool (CI asks before its tests).
[ "$FLAVOR" != --check ] || { log "every host tool is there"; exit 0; }

ENVFILE=$CACHE/$FLAVOR.env
if ! sel=$(select_abi); then
    # No apt lists (or nothing complete): fall back to a previous result.
    if [ -f "$ENVFILE" ] && [ -z "${PPM_VM_KABI:-}" ]; then
        log "apt-cache finds no complete 6.1 kernel set; reusing cached $(grep ^KREL= "$ENVFILE")"
        # shellcheck disable=SC1090
        . "$ENVFILE"
        echo "vmlinuz: $VMLINUZ"; echo "kernel:  $KERNEL"; echo "modules: $MODDIR"
        exit 0
    fi
    die "no linux-6.1.0-${PPM_VM_KABI:-NN} ABI with image+headers (std and rt), linux-kbuild-6.1 and linux-source-6.1 all at the same version in apt. Run 'apt-get update' first (or set PPM_VM_KABI to an available NN)."
fi
read -r NN DEBVER <<<"$sel"
KREL=6.1.0-$NN-$VARIANT
KDIR=$CACHE/$KREL
STAMP="$DEBVER recipe=$RECIPE_VERSION modules=$WANTED_IMAGE_MODULES board=$(cksum < "$HERE/ppm_spi_board.c" | cut -d' ' -f1)"

if [ -f "$KDIR/.stamp" ] && [ "$(cat "$KDIR/.stamp")" = "$STAMP" ]; then
    log "cached: $KREL ($DEBVER)"
else
    log "preparing $KREL (Debian $DEBVER) in $KDIR"
    rm -rf "$KDIR"
    # Scratch space (~700 MB, deleted at the end) in RAM when possible:
    # unpacking the packages (tens of thousands of header files) took 15-20 s
    # on this machine's disk and under 5 s on tmpfs. PPM_VM_TMP overrides.
    scratch=${PPM_VM_TMP:-}
    if [ -z "$scratch" ]; then
        scratch=${TMPDIR:-/tmp}
        if [ -d /dev/shm ] && [ -w /dev/shm ] &&
           [ "$(df -Pk /dev/shm | awk 'NR==2 {print $4}')" -gt 2000000 ]; then
            scratch=/dev/shm
        fi
    fi
    WORK=$(mktemp -d "$scratch/ppm-vm-prepare.XXXXXX")
    mkdir -p "$WORK/debs" "$WORK/root" "$WORK/build"
    trap 'rm -rf "$WORK"' EXIT

    # The GPL source files are shared by both flavours: extract them once
    # per Debian version (the linux-source .deb is 140 MB of xz). .done
    # lists the files, so that a cache from an older list is redone.
    SRC=$CACHE/src-$DEBVER
    src_done() { [ -f "$SRC/.done" ] && [ "$(cat "$SRC/.done")" = "$SRC_FILES" ]; }
    PKGS="linux-image-$KREL-unsigned linux-headers-$KREL linux-headers-6.1.0-$NN-common$COMMON_SUFFIX linux-kbuild-6.1"
    src_done || PKGS="$PKGS linux-source-6.1"

    # --- download (apt-get download writes to the current directory).
    # shellcheck disable=SC2046 # one pkg=version per word
    ( cd "$WORK/debs" && apt-get download -q $(for p in $PKGS; do printf '%s=%s ' "$p" "$DEBVER"; done) ) \
        >"$WORK/download.log" 2>&1 || { cat "$WORK/download.log" >&2; die "apt-get download failed (stale apt lists? run apt-get update)"; }

    log "  downloaded: $PKGS"
    # --- unpack image, headers, kbuild (not the source: see below).
    for deb in "$WORK"/debs/linux-{image,headers,kbuild}-*.deb; do
        dpkg-deb -x "$deb" "$WORK/root"
    done
    HDR=$WORK/root/usr/src/linux-headers-$KREL
    [ -f "$HDR/Makefile" ] || die "headers Makefile missing in $HDR"
    # Debian's per-flavour Makefile includes the common tree by absolute
    # path (/usr/src/...); point it at our unpacked copy instead.
    sed -i "s#^include /usr/src/#include $WORK/root/usr/src/#" "$HDR/Makefile"
    grep -q "^include $WORK/root/usr/src/" "$HDR/Makefile" ||
        die "unexpected headers Makefile layout: $(cat "$HDR/Makefile")"

    log "  unpacked"
    # --- extract only the source files we need, streaming the tarball out
    # of the .deb instead of unpacking it.
    if ! src_done; then
        rm -rf "$SRC.tmp"; mkdir -p "$SRC.tmp"
        # shellcheck disable=SC2046 # one path per word
        dpkg-deb --fsys-tarfile "$(echo "$WORK"/debs/linux-source-6.1_*.deb)" |
            tar -xOf - ./usr/src/linux-source-6.1.tar.xz |
            tar -xJf - -C "$SRC.tmp" --strip-components=1 \
                $(for f in $SRC_FILES; do echo "linux-source-6.1/$f"; done)
        echo "$SRC_FILES" > "$SRC.tmp/.done"
        rm -rf "$SRC"; mv "$SRC.tmp" "$SRC" 2>/dev/null || true  # a parallel run may have won
    fi
    B=$WORK/build
    for f in $SRC_FILES; do cp "$SRC/$f" "$B/"; done
    cp "$HERE/ppm_spi_board.c" "$B/"

    # irq_sim.c is normally built in and calls handle_simple_irq(irq_to_desc(n));
    # irq_to_desc is not exported to modules. generic_handle_irq(n) does the
    # same lookup inside the kernel and then calls desc->handle_irq, which
    # irq_sim_domain_map() set to handle_simple_irq, so behaviour is identical.
    sed -i 's/handle_simple_irq(irq_to_desc(irqnum));/generic_handle_irq(irqnum);/' "$B/irq_sim.c"
    grep -q 'generic_handle_irq(irqnum);' "$B/irq_sim.c" || die "could not patch irq_sim.c (source changed?)"
    grep -q 'irq_to_desc' "$B/irq_sim.c" && die "irq_sim.c still uses irq_to_desc (source changed?)"
    # Built-in code has no license tag; modules without one cannot use GPL symbols.
    grep -q MODULE_LICENSE "$B/irq_sim.c" || {
        printf '\n#include <linux/module.h>\nMODULE_LICENSE("GPL");\nMODULE_DESCRIPTION("Interrupt simulator (out-of-tree build for tests)");\n' >> "$B/irq_sim.c"; }
    echo 'obj-m := irq_sim.o gpio-sim.o spi-gpio.o ppm_spi_board.o' > "$B/Kbuild"
    log "  building gpio-sim.ko, irq_sim.ko, spi-gpio.ko, ppm_spi_board.ko"
    make -C "$HDR" M="$B" -j2 modules >"$WORK/build.log" 2>&1 ||
        { cat "$WORK/build.log" >&2; die "module build failed (log above)"; }
    for m in irq_sim gpio-sim spi-gpio ppm_spi_board; do
        [ -f "$B/$m.ko" ] || die "$m.ko not built"
        vm=$(modinfo_field "$B/$m.ko" vermagic)
        case "$vm" in "$KREL "*) ;; *) die "$m.ko has vermagic '$vm', expected $KREL" ;; esac
    done

    log "  built"
    # --- assemble the result.
    STAGE=$CACHE/.stage-$KREL.$$
    rm -rf "$STAGE"; mkdir -p "$STAGE/modules"
    cp "$WORK/root/boot/vmlinuz-$KREL" "$STAGE/vmlinuz"
    cp "$WORK/root/boot/config-$KREL" "$STAGE/config"
    # QEMU can boot the uncompressed ELF vmlinux directly through its PVH
    # entry point (CONFIG_PVH=y). That skips the in-guest xz decompression
    # of the bzImage, which takes ~5 s under TCG with -icount: half the boot.
    # Fall back to the bzImage when the kernel is not xz-compressed or lacks
    # the PVH note (ELF note type 0x12, XEN_ELFNOTE_PHYS32_ENTRY).
    # (pipefail is off here: xz stops after the first stream and head/grep -q
    # exit early, so the producers legitimately die of SIGPIPE.)
    set +o pipefail
    off=$(grep -abo $'\xfd7zXZ\x00' "$STAGE/vmlinuz" | head -n1 | cut -d: -f1)
    if [ -n "$off" ] &&
       tail -c +$((off + 1)) "$STAGE/vmlinuz" | xz -dc --single-stream > "$STAGE/vmlinux" 2>/dev/null &&
       readelf -n "$STAGE/vmlinux" 2>/dev/null | grep -q 'Unknown note type: (0x00000012)'; then
        KERNEL_FILE=vmlinux
    else
        log "  no PVH-bootable vmlinux could be extracted; booting the bzImage (slower)"
        rm -f "$STAGE/vmlinux"
        KERNEL_FILE=vmlinuz
    fi
    set -o pipefail
    echo "$KERNEL_FILE" > "$STAGE/kernel-file"

    MODOUT=$STAGE/modules
    BUILTIN_LIST=$WORK/root/lib/modules/$KREL/modules.builtin
    : > "$MODOUT/load.order"
    # (pure parameter expansion: ~4000 modules, forking per module is slow)
    while IFS= read -r -d '' f; do
        b=${f##*/}; b=${b%.ko}
        MODPATH[${b//-/_}]=$f
    done < <(find "$WORK/root/lib/modules/$KREL/kernel" -name '*.ko' -print0)
    MODPATH[irq_sim]=$B/irq_sim.ko
    MODPATH[gpio_sim]=$B/gpio-sim.ko
    MODPATH[spi_gpio]=$B/spi-gpio.ko
    for m in $WANTED_IMAGE_MODULES irq_sim gpio_sim spi_gpio; do add_module "$m"; done
    # Loaded by the SPI test itself (its parameters name the lines).
    cp "$B/ppm_spi_board.ko" "$MODOUT/"

    # Facts worth failing early on.
    grep -q '^CONFIG_GPIO_CDEV=y' "$STAGE/config" || die "kernel lacks CONFIG_GPIO_CDEV"
    grep -q '^CONFIG_TRACING=y' "$STAGE/config" || die "kernel lacks CONFIG_TRACING"
    grep -q '^CONFIG_DEVTMPFS=y' "$STAGE/config" || die "kernel lacks CONFIG_DEVTMPFS"
    grep -q '^CONFIG_SPI_SPIDEV=[ym]' "$STAGE/config" || die "kernel lacks CONFIG_SPI_SPIDEV"
    grep -q '^CONFIG_SPI_SPIDEV=y' "$STAGE/config" ||
        die "spidev is a module in this kernel (CONFIG_SPI_SPIDEV=m): add spidev to WANTED_IMAGE_MODULES"

    echo "$STAMP" > "$STAGE/.stamp"
    mv "$STAGE" "$KDIR"
    rm -rf "$WORK"; trap - EXIT
fi

{
    echo "KREL=$KREL"
    echo "DEBVER=$DEBVER"
    # KERNEL: what run.sh boots (vmlinux via PVH when available).
    echo "KERNEL=$KDIR/$(cat "$KDIR/kernel-file")"
    echo "VMLINUZ=$KDIR/vmlinuz"
    echo "MODDIR=$KDIR/modules"
} > "$ENVFILE.tmp"
mv "$ENVFILE.tmp" "$ENVFILE"
log "modules (load order): $(tr '\n' ' ' < "$KDIR/modules/load.order")"
echo "vmlinuz: $KDIR/vmlinuz"
echo "kernel:  $KDIR/$(cat "$KDIR/kernel-file")"
echo "modules: $KDIR/modules"
