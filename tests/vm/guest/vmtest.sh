# Helpers for guest test scripts: `. /lib/vmtest.sh` at the top of test.sh.
# busybox sh (ash) syntax. Everything a test writes under /out (the working
# directory of test.sh) is copied to the host's OUTDIR.

export VMTEST_OUT=/out
VMTEST_TRACEFS=/sys/kernel/tracing
VMTEST_SIMFS=/sys/kernel/config/gpio-sim
# Per-CPU ring buffer size. One gpio_value event takes ~32 bytes; 8 MiB
# holds well over 200k events, far above the ~20k a test produces.
: "${VMTEST_TRACE_BUF_KB:=8192}"

vmtest_die() { echo "vmtest: FAIL: $*" >&2; exit 1; }

# make_sim_chip LABEL NUM_LINES [LINE_NAME...]
# Creates a one-bank gpio-sim chip through configfs and prints its
# character device, e.g. /dev/gpiochip0. Line i gets the i-th name given.
make_sim_chip() {
    [ $# -ge 2 ] || vmtest_die "usage: make_sim_chip LABEL NUM_LINES [NAMES...]"
    _label=$1 _n=$2; shift 2
    _dev=$VMTEST_SIMFS/$_label
    mkdir "$_dev" || vmtest_die "cannot create $_dev"
    mkdir "$_dev/bank0"
    echo "$_label" > "$_dev/bank0/label"
    echo "$_n" > "$_dev/bank0/num_lines"
    _i=0
    for _name in "$@"; do
        mkdir "$_dev/bank0/line$_i"
        echo "$_name" > "$_dev/bank0/line$_i/name"
        _i=$((_i + 1))
    done
    echo 1 > "$_dev/live" || vmtest_die "cannot bring gpio-sim chip $_label live"
    _chip=$(cat "$_dev/bank0/chip_name")
    [ -c "/dev/$_chip" ] || vmtest_die "/dev/$_chip did not appear"
    echo "/dev/$_chip"
}

# remove_sim_chip LABEL: undoes make_sim_chip (lines must be released).
remove_sim_chip() {
    _dev=$VMTEST_SIMFS/$1
    echo 0 > "$_dev/live"
    for _l in "$_dev"/bank0/line*; do [ -d "$_l" ] && rmdir "$_l"; done
    rmdir "$_dev/bank0" "$_dev"
}

# sim_attr_dir CHIPDEV LINE: sysfs directory with gpio-sim's per-line
# 'value' (what the line carries, read-only view of outputs) and 'pull'
# (writing pull-up/pull-down drives an *input* line, like an external signal).
sim_attr_dir() { echo "/sys/bus/gpio/devices/${1#/dev/}/sim_gpio$2"; }
sim_pull()  { echo "$3" > "$(sim_attr_dir "$1" "$2")/pull"; }   # CHIPDEV LINE pull-up|pull-down
sim_value() { cat "$(sim_attr_dir "$1" "$2")/value"; }          # CHIPDEV LINE -> 0|1

# sim_chip_base CHIPDEV: global GPIO number of line 0. The gpio_value
# tracepoint reports global numbers: line offset = gpio - base.
sim_chip_base() {
    # The legacy sysfs class device (gpiochipBASE) is a sibling of the
    # gpio_device under the gpio-sim platform device (one bank per device).
    _p=$(readlink -f "/sys/bus/gpio/devices/${1#/dev/}") || return 1
    for _c in "${_p%/*}"/gpio/gpiochip*; do
        [ -f "$_c/base" ] && { cat "$_c/base"; return 0; }
    done
    return 1
}

# sysfs_gpio_out CHIPDEV LINE: claims LINE as an output through the legacy
# /sys/class/gpio interface (CONFIG_GPIO_SYSFS=y) and prints the directory
# whose 'value' file drives it; each write is a gpiod_set_value() and so
# produces a gpio_value "set" trace event. Lets shell tests drive outputs
# without a gpioset binary.
sysfs_gpio_out() {
    _g=$(( $(sim_chip_base "$1") + $2 ))
    [ -d /sys/class/gpio/gpio$_g ] || echo "$_g" > /sys/class/gpio/export
    echo out > /sys/class/gpio/gpio$_g/direction
    echo /sys/class/gpio/gpio$_g
}

# start_gpio_trace [EVENT...]: clear the trace buffer and start recording
# gpio tracepoints (default: gpio_value) with the 'mono' clock, i.e. the
# same clock as CLOCK_MONOTONIC. Also records trace_marker writes.
start_gpio_trace() {
    _t=$VMTEST_TRACEFS
    echo 0 > $_t/tracing_on
    echo mono > $_t/trace_clock
    echo "$VMTEST_TRACE_BUF_KB" > $_t/buffer_size_kb
    echo 0 > $_t/events/enable
    [ $# -gt 0 ] || set -- gpio_value
    for _e in "$@"; do
        echo 1 > "$_t/events/gpio/$_e/enable" || vmtest_die "no tracepoint gpio:$_e"
    done
    echo > $_t/trace          # clears the buffer
    echo 1 > $_t/tracing_on
}

# stop_gpio_trace OUTFILE: stop recording and save the human-readable trace
# (timestamps in seconds with microsecond resolution). Fails if the ring
# buffer overflowed, since then edges are missing.
stop_gpio_trace() {
    [ $# -eq 1 ] || vmtest_die "usage: stop_gpio_trace OUTFILE"
    _t=$VMTEST_TRACEFS
    echo 0 > $_t/tracing_on
    cat $_t/trace > "$1"
    echo 0 > $_t/events/enable
    _over=$(awk '/^overrun:/ {s += $2} END {print s + 0}' $_t/per_cpu/cpu*/stats)
    [ "$_over" = 0 ] || vmtest_die "trace buffer overran ($_over events lost); raise VMTEST_TRACE_BUF_KB"
}

# spi_gpio_bus LABEL BUS SCK MOSI CS: an SPI master (the kernel's spi-gpio,
# bit-banging through gpiolib) on lines SCK, MOSI, CS (offsets) of the
# gpio-sim chip LABEL (made with make_sim_chip), with one device BUS.0
# (mode 0) bound to spidev; prints its node, /dev/spidevBUS.0. spi-bitbang
# and spi-gpio are loaded at boot; ppm_spi_board.ko (tests/vm/
# ppm_spi_board.c) adds the gpiod lookups, platform device spi_gpio.BUS and
# the SPI device, which no driver claims until driver_override names spidev.
spi_gpio_bus() {
    [ $# -eq 5 ] || vmtest_die "usage: spi_gpio_bus LABEL BUS SCK MOSI CS"
    insmod /lib/modules/ppm_spi_board.ko chip="$1" bus="$2" sck="$3" mosi="$4" cs="$5" ||
        vmtest_die "insmod ppm_spi_board failed: $(dmesg | grep -E 'spi|gpio' | tail -n 5)"
    _d=spi$2.0
    [ -d /sys/bus/spi/devices/$_d ] || vmtest_die "no SPI device $_d"
    echo spidev > /sys/bus/spi/devices/$_d/driver_override
    echo "$_d" > /sys/bus/spi/drivers/spidev/bind || vmtest_die "cannot bind spidev to $_d"
    _i=0
    while [ ! -c "/dev/spidev$2.0" ] && [ $_i -lt 50 ]; do sleep 0.1; _i=$((_i + 1)); done
    [ -c "/dev/spidev$2.0" ] || vmtest_die "/dev/spidev$2.0 did not appear"
    echo "/dev/spidev$2.0"
}

# trace_mark TEXT: put a line into the trace (shows as tracing_mark_write).
trace_mark() { echo "$*" > $VMTEST_TRACEFS/trace_marker; }
