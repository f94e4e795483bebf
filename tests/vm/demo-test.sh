#!/bin/sh
# Demo guest test for tests/vm/run.sh (runs inside the VM under busybox sh):
#   tests/vm/run.sh std target/vm/demo-std tests/vm/demo-test.sh
# Creates a gpio-sim chip with lines GPIO17..GPIO20, records the gpio
# tracepoints while
#   - line 0 (GPIO17) is an input driven from "outside" through gpio-sim's
#     'pull' attribute (this changes the simulated level without calling
#     gpiolib, so it produces NO trace event; reading the line through
#     gpiolib produces "get" events), and
#   - line 1 (GPIO18) is an output toggled through /sys/class/gpio (each
#     write is gpiod_set_value(): one "set" event per edge),
# and saves the trace to /out/gpio_trace.txt (OUTDIR/gpio_trace.txt on the host).
set -eu
. /lib/vmtest.sh

chip=$(make_sim_chip demo 4 GPIO17 GPIO18 GPIO19 GPIO20)
base=$(sim_chip_base "$chip")
echo "demo: $chip, lines 0..3 = global GPIOs $base..$((base + 3))"
grep -A5 "^$(basename "$chip")" /sys/kernel/debug/gpio || true

start_gpio_trace gpio_value gpio_direction

# Input: GPIO17, level set by the simulated outside world.
echo "$base" > /sys/class/gpio/export
echo in > "/sys/class/gpio/gpio$base/direction"
for pull in pull-up pull-down pull-up pull-down; do
    sim_pull "$chip" 0 "$pull"
    want=0; [ "$pull" = pull-up ] && want=1
    got=$(cat "/sys/class/gpio/gpio$base/value")
    [ "$got" = "$want" ] || vmtest_die "GPIO17 reads $got after $pull, want $want"
done

# Output: GPIO18, 5 pulses of 1 ms (virtual time: costs no wall time).
out=$(sysfs_gpio_out "$chip" 1)
trace_mark "pulses start"
i=0
while [ $i -lt 5 ]; do
    echo 1 > "$out/value"; usleep 1000
    [ "$(sim_value "$chip" 1)" = 1 ] || vmtest_die "GPIO18 did not go high"
    echo 0 > "$out/value"; usleep 1000
    i=$((i + 1))
done
trace_mark "pulses end"

stop_gpio_trace /out/gpio_trace.txt

# The trace must hold one "set" event per edge on GPIO18 (plus the initial
# "set 0" from switching it to output) and none for the pull changes.
sets=$(grep -c "gpio_value: $((base + 1)) set" /out/gpio_trace.txt || true)
[ "$sets" = 11 ] || vmtest_die "expected 11 set events on GPIO18, found $sets"
pull_sets=$(grep -c "gpio_value: $base set" /out/gpio_trace.txt || true)
[ "$pull_sets" = 0 ] || vmtest_die "unexpected set events on GPIO17"
echo "demo: trace has $sets set events on GPIO18:"
grep "gpio_value: $((base + 1)) set" /out/gpio_trace.txt
echo "demo: OK"
