#!/bin/sh
# Guest script of the real-kernel test (tests/tests/vm.rs): the whole
# pipeline on a gpio-sim line, recorded by the kernel's gpio tracepoint.
#   - error paths that a kernel can produce: a missing line, a missing chip,
#     a line already in use (by a running ppmd);
#   - udp-ingress and ppmd on GPIO18 of a gpio-sim chip, commands from
#     ppm-send over loopback at 50 Hz, then SIGTERM to ppmd.
#   - one ppmd with two outputs on GPIO19 and GPIO20 (one request), fed by
#     two udp-ingress, traced with the calls that set the values.
#   - ppmd in follow timing on GPIO18, commands from ppm-send at 50 Hz.
#   - ppmd in grid and follow timing on GPIO18 while ppm-interfere holds its
#     CPU in bursts: interfere_{grid,follow}_* files.
# Results in /out: gpio_trace.txt, *.log, chip.txt, ppmd_exit.txt,
# debug_gpio_after.txt, frames.jsonl, two_trace.txt, two_ppmd_exit.txt,
# follow_trace.txt, follow_frames.jsonl, follow_ppmd_exit.txt.
#   - ppm-capture reading GPIO17 while pull-timed drives it through
#     gpio-sim's pull attribute: readback_frames.jsonl, readback_capture.log,
#     readback_pull.txt, readback_pull.log.
#   - ppmd's spi output on the kernel's spi-gpio master (bit-banging three
#     lines of a second gpio-sim chip, "ppm-spi") through spidev, commands
#     from ppm-send at 50 Hz: spi_trace.txt (the gpio_value events of SCK,
#     MOSI and CS), spi_lines.txt (their global GPIO numbers, the bit rate,
#     the SPI mode), spi_ppmd.log, spi_ppmd_exit.txt, spi_frames.jsonl.
#   - SBUS on ttyS1 and through the same spidev: sbus_tty.txt,
#     sbus_ppmd.log, sbus_ppmd_exit.txt, sbus_frames.jsonl (serial; the
#     bytes are the host's serial1.bin), sbus_spi_trace.txt,
#     sbus_spi_ppmd.log, sbus_spi_ppmd_exit.txt, sbus_spi_frames.jsonl.
#   - CRSF on ttyS2: crsf_tty.txt, crsf_tty_before.txt, crsf_uartclk.txt,
#     crsf_ppmd.log, crsf_ppmd_exit.txt, crsf_frames.jsonl,
#     crsf_proc_serial.txt (the bytes are the host's serial2.bin).
set -eu
. /lib/vmtest.sh

# stop_ppmd PID EXIT TRACE: SIGTERM to ppmd, its exit status in /out/EXIT.txt,
# and the trace in /out/TRACE.txt plus the same events with nanosecond
# timestamps in /out/TRACE_raw.txt (the text has microseconds; the raw
# format keeps the time but not the fields, and lists the events in the same
# order, so the host pairs the two line by line).
stop_ppmd() {
    kill -TERM "$1"
    _status=0
    wait "$1" || _status=$?
    echo "$_status" > "/out/$2.txt"
    stop_gpio_trace "/out/$3.txt"
    echo 1 > $VMTEST_TRACEFS/options/raw
    cat $VMTEST_TRACEFS/trace > "/out/$3_raw.txt"
    echo 0 > $VMTEST_TRACEFS/options/raw
}

# end_ppmd PID EXIT: SIGTERM to ppmd and its exit status in /out/EXIT.txt.
end_ppmd() {
    kill -TERM "$1"
    _status=0
    wait "$1" || _status=$?
    echo "$_status" > "/out/$2.txt"
}

# spi_trace NAME: stops the gpio trace and keeps the SPI bus's events in
# /out/NAME.txt.
spi_trace() {
    stop_gpio_trace "/tmp/$1_all.txt"
    grep -E "gpio_value: ($spi_base|$((spi_base + 1))|$((spi_base + 2))) " "/tmp/$1_all.txt" \
        > "/out/$1.txt" || true
    rm -f "/tmp/$1_all.txt"
}

chip=$(make_sim_chip ppm 4 GPIO17 GPIO18 GPIO19 GPIO20)
base=$(sim_chip_base "$chip")
echo "$chip $base" > /out/chip.txt
uname -v > /out/uname.txt

# Grid timing where a run sets none: these runs count frames on the grid
# (follow, the default, runs with --timing follow below).
cat > /tmp/ppm.toml <<CONF
name = "vm"
[ingress]
listen = "127.0.0.1:5005"
[ipc]
root = "/tmp/ppm-ipc"
[ppm]
timing = "grid"
CONF

# Error paths (each must fail, with its message in the log).
if ppmd --config /tmp/ppm.toml --output "gpio:$chip:GPIO99" 2> /out/err_missing_line.log; then
    vmtest_die "ppmd accepted a missing line"
fi
if ppmd --config /tmp/ppm.toml --output "gpio:nosuchchip:GPIO18" 2> /out/err_missing_chip.log; then
    vmtest_die "ppmd accepted a missing chip"
fi

start_gpio_trace gpio_value
udp-ingress --config /tmp/ppm.toml 2> /out/ingress.log &
ingress=$!
ppmd --config /tmp/ppm.toml --output "gpio:$chip:GPIO18" --frame-log /out/frames.jsonl 2> /out/ppmd.log &
ppmd=$!
sleep 1
if ppmd --config /tmp/ppm.toml --name other --output "gpio:$chip:GPIO18" 2> /out/err_busy.log; then
    vmtest_die "a second ppmd got the line in use"
fi
ppm-send --to 127.0.0.1:5005 --rate 50 --count 50 '[1000, 1200, 1700, 2000]'
sleep 0.5
stop_ppmd "$ppmd" ppmd_exit gpio_trace
cat /sys/kernel/debug/gpio > /out/debug_gpio_after.txt
kill -TERM "$ingress"
wait "$ingress" || true

# Two outputs of one ppmd on GPIO19 and GPIO20 of the same chip: one
# request, so edges due together are set in one call. The function tracer
# marks each call of gpiod_set_array_value_complex (one per
# GPIO_V2_LINE_SET_VALUES ioctl) between the gpio_value events.
cat > /tmp/two.toml <<CONF
[ipc]
root = "/tmp/ppm-ipc"
[ppm]
timing = "grid"
[[outputs]]
name = "two-a"
output = "gpio:$chip:GPIO19"
ingress.listen = "127.0.0.1:5006"
[[outputs]]
name = "two-b"
output = "gpio:$chip:GPIO20"
ingress.listen = "127.0.0.1:5007"
[outputs.ppm]
order = "TAER"
CONF
echo gpiod_set_array_value_complex > $VMTEST_TRACEFS/set_ftrace_filter \
    || vmtest_die "cannot trace gpiod_set_array_value_complex"
echo function > $VMTEST_TRACEFS/current_tracer || vmtest_die "no function tracer"
start_gpio_trace gpio_value
udp-ingress --config /tmp/two.toml --name two-a 2> /out/two_ingress_a.log &
ing_a=$!
udp-ingress --config /tmp/two.toml --name two-b 2> /out/two_ingress_b.log &
ing_b=$!
ppmd --config /tmp/two.toml 2> /out/two_ppmd.log &
ppmd2=$!
sleep 1
ppm-send --to 127.0.0.1:5006 --rate 50 --count 50 '[1000, 1200, 1700, 2000]' &
send_a=$!
ppm-send --to 127.0.0.1:5007 --rate 50 --count 50 '[2000, 1100, 1600, 1300]'
wait "$send_a"
sleep 0.5
stop_ppmd "$ppmd2" two_ppmd_exit two_trace
echo nop > $VMTEST_TRACEFS/current_tracer
kill -TERM "$ing_a" "$ing_b"
wait "$ing_a" "$ing_b" || true

# Follow timing on GPIO18 (released by the first ppmd): frames start when
# the commands come. The line is named without its chip (gpio:LINE): ppmd
# finds the chip that has it.
start_gpio_trace gpio_value
udp-ingress --config /tmp/ppm.toml --listen 127.0.0.1:5008 2> /out/follow_ingress.log &
fing=$!
ppmd --config /tmp/ppm.toml --timing follow --output gpio:GPIO18 \
    --frame-log /out/follow_frames.jsonl 2> /out/follow_ppmd.log &
fppmd=$!
sleep 1
ppm-send --to 127.0.0.1:5008 --rate 50 --count 50 --sweep 1:1000:1490:2s '[1000, 1200, 1700, 2000]'
sleep 0.5
stop_ppmd "$fppmd" follow_ppmd_exit follow_trace
kill -TERM "$fing"
wait "$fing" || true

# A held-up timing thread: ppm-interfere holds ppmd's CPU at SCHED_FIFO 90
# (above ppmd's 80) for 100..500 us every 5..60 ms while ppmd runs grid, then
# follow timing on GPIO18: interfere_TIMING_trace.txt, _frames.jsonl,
# _ppmd.log, _ppmd_exit.txt, _bursts.txt (start and length of each burst).
for timing in grid follow; do
    start_gpio_trace gpio_value
    udp-ingress --config /tmp/ppm.toml --listen 127.0.0.1:5009 \
        2> "/out/interfere_${timing}_ingress.log" &
    iing=$!
    ppmd --config /tmp/ppm.toml --timing "$timing" --output "gpio:$chip:GPIO18" \
        --frame-log "/out/interfere_${timing}_frames.jsonl" 2> "/out/interfere_${timing}_ppmd.log" &
    ippmd=$!
    sleep 1
    ppm-interfere --cpu last --priority 90 --burst-us 100..500 --gap-ms 5..60 --duration 1500ms \
        --log "/out/interfere_${timing}_bursts.txt" > "/out/interfere_${timing}.txt" 2>&1 &
    interferer=$!
    ppm-send --to 127.0.0.1:5009 --rate 50 --count 60 '[1000, 1200, 1700, 2000]'
    wait "$interferer" || vmtest_die "ppm-interfere failed: $(cat "/out/interfere_${timing}.txt")"
    sleep 0.5
    stop_ppmd "$ippmd" "interfere_${timing}_ppmd_exit" "interfere_${timing}_trace"
    kill -TERM "$iing"
    wait "$iing" || true
done

# jitter --capture: GPIO17 requested as an input with edge detection, driven
# from outside by pull-ppm (ppmd's timing loop writing gpio-sim's pull
# attribute); the kernel timestamps each edge.
jitter --capture "$chip:GPIO17" -D 2s --expect 1000,1200,1700,2000,1500,1500,1500,1500 \
    --plot /out/capture.svg > /out/capture.txt 2> /out/capture.log &
capture=$!
sleep 0.3
pull-ppm "$(sim_attr_dir "$chip" 0)/pull" 60 1000,1200,1700,2000 2> /out/pull-ppm.log
wait "$capture" || vmtest_die "jitter --capture failed: $(cat /out/capture.log)"

# ppm-capture reads PPM from GPIO17 (an input with both edges and kernel
# timestamps) while pull-timed drives it through gpio-sim's pull attribute
# on its own clock (8 channels 1100..1800 us, 300 us pulses, 22.5 ms
# frames), recording CLOCK_MONOTONIC before and after every write:
# readback_frames.jsonl (the frames read), readback_capture.log (its
# summary), readback_pull.txt (the writes), readback_pull.log.
ppm-capture --input "gpio:$chip:GPIO17" --log /out/readback_frames.jsonl --duration 4s \
    --quiet --channels 8 --idle-level low 2> /out/readback_capture.log &
rcap=$!
# The driver starts once the line is requested (ppm-capture says so).
_i=0
while ! grep -q "reading" /out/readback_capture.log && [ $_i -lt 100 ]; do
    sleep 0.05
    _i=$((_i + 1))
done
pull-timed "$(sim_attr_dir "$chip" 0)/pull" 120 1100,1200,1300,1400,1500,1600,1700,1800 \
    /out/readback_pull.txt 2> /out/readback_pull.log ||
    vmtest_die "pull-timed failed: $(cat /out/readback_pull.log)"
wait "$rcap" || vmtest_die "ppm-capture failed: $(cat /out/readback_capture.log)"

# The spi output: ppmd sends each frame as one spidev transfer on MOSI of the
# kernel's spi-gpio master, which bit-bangs SCK, MOSI and CS (lines 0, 1, 2
# of chip ppm-spi) through gpiolib: every bit is traced. spi-gpio ignores the
# rate (it clocks as fast as gpiolib goes, here ~1.6 us a bit, so a 12 ms
# frame at 100 kHz shifts out in ~2 ms); the bits are what is checked.
spi_hz=100000
spi_chip=$(make_sim_chip ppm-spi 3 SPI_SCK SPI_MOSI SPI_CS)
spi_base=$(sim_chip_base "$spi_chip")
spidev=$(spi_gpio_bus ppm-spi 0 0 1 2)
# Global GPIO numbers, as the gpio_value tracepoint shows them (base + offset).
printf 'sck %s\nmosi %s\ncs %s\nhz %s\nmode 0\n' \
    "$spi_base" $((spi_base + 1)) $((spi_base + 2)) "$spi_hz" > /out/spi_lines.txt
cat > /tmp/spi.toml <<CONF
name = "vm-spi"
[ingress]
listen = "127.0.0.1:5009"
[ipc]
root = "/tmp/ppm-ipc"
[ppm]
timing = "grid"
[ppmd]
spi_hz = $spi_hz
CONF
# ~2600 events a frame (two SCK edges a bit, MOSI's changes, CS).
VMTEST_TRACE_BUF_KB=32768 start_gpio_trace gpio_value
udp-ingress --config /tmp/spi.toml 2> /out/spi_ingress.log &
sing=$!
ppmd --config /tmp/spi.toml --output "spi:$spidev" --frame-log /out/spi_frames.jsonl \
    2> /out/spi_ppmd.log &
sppmd=$!
sleep 1
ppm-send --to 127.0.0.1:5009 --rate 50 --count 50 '[1000, 1200, 1700, 2000]'
sleep 0.5
end_ppmd "$sppmd" spi_ppmd_exit
spi_trace spi_trace
kill -TERM "$sing"
wait "$sing" || true

# SBUS on the guest's second serial port (ttyS1, a 16550 whose bytes QEMU
# writes to the host's OUTDIR/serial1.bin) and through spidev (the same
# spi-gpio bus, true SBUS at 100 kHz): follow timing, encoded for EdgeTX,
# the example command with aux12 at 1900. sbus_tty.txt: the settings the
# kernel holds for ttyS1 while ppmd has it open.
cat > /tmp/sbus.toml <<CONF
name = "vm-sbus"
[ingress]
listen = "127.0.0.1:5010"
[ipc]
root = "/tmp/ppm-ipc"
[ppm]
protocol = "sbus"
receiver = "edgetx"
timing = "follow"
# This 16550's clock makes 115200 of SBUS's 100000: a degraded run.
[rt]
allow_degraded = true
CONF
sbus_cmd='{"ail": 1000, "ele": 1200, "thr": 1700, "rud": 2000, "aux12": 1900}'
udp-ingress --config /tmp/sbus.toml 2> /out/sbus_ingress.log &
bing=$!
ppmd --config /tmp/sbus.toml --output serial:/dev/ttyS1 --frame-log /out/sbus_frames.jsonl \
    2> /out/sbus_ppmd.log &
bppmd=$!
sleep 1
tty-settings /dev/ttyS1 > /out/sbus_tty.txt 2>&1 || true
ppm-send --to 127.0.0.1:5010 --rate 50 --count 50 "$sbus_cmd"
sleep 0.5
end_ppmd "$bppmd" sbus_ppmd_exit
VMTEST_TRACE_BUF_KB=32768 start_gpio_trace gpio_value
ppmd --config /tmp/sbus.toml --output "spi:$spidev" --frame-log /out/sbus_spi_frames.jsonl \
    2> /out/sbus_spi_ppmd.log &
bppmd=$!
sleep 1
ppm-send --to 127.0.0.1:5010 --rate 50 --count 50 "$sbus_cmd"
sleep 0.5
end_ppmd "$bppmd" sbus_spi_ppmd_exit
spi_trace sbus_spi_trace
kill -TERM "$bing"
wait "$bing" || true

# CRSF on the guest's third serial port (ttyS2, a 16550 whose bytes QEMU
# writes to the host's OUTDIR/serial2.bin): follow timing, encoded for
# Betaflight, four commands in turn (aileron 1100, 1300, 1600, 1900), ten
# each at 50 Hz. crsf_tty.txt: the settings the kernel holds for ttyS2
# while ppmd has it open (crsf_tty_before.txt: before ppmd opened it);
# crsf_uartclk.txt: the UART's clock (sysfs); crsf_proc_serial.txt: the
# kernel's per-port counters after ppmd exited (tx: bytes sent).
cat > /tmp/crsf.toml <<CONF
name = "vm-crsf"
[ingress]
listen = "127.0.0.1:5011"
[ipc]
root = "/tmp/ppm-ipc"
[ppm]
protocol = "crsf"
receiver = "betaflight"
timing = "follow"
CONF
# The 16550 cannot make 420000 baud: without rt.allow_degraded ppmd
# refuses to start (crsf_refused_exit.txt, crsf_refused.log).
refused=0
ppmd --config /tmp/crsf.toml --output serial:/dev/ttyS2 2> /out/crsf_refused.log || refused=$?
echo "$refused" > /out/crsf_refused_exit.txt
printf '[rt]\nallow_degraded = true\n' >> /tmp/crsf.toml
cat /sys/class/tty/ttyS2/uartclk > /out/crsf_uartclk.txt 2>&1 || true
tty-settings /dev/ttyS2 > /out/crsf_tty_before.txt 2>&1 || true
udp-ingress --config /tmp/crsf.toml 2> /out/crsf_ingress.log &
cing=$!
ppmd --config /tmp/crsf.toml --output serial:/dev/ttyS2 --frame-log /out/crsf_frames.jsonl \
    2> /out/crsf_ppmd.log &
cppmd=$!
sleep 1
tty-settings /dev/ttyS2 > /out/crsf_tty.txt 2>&1 || true
for ail in 1100 1300 1600 1900; do
    ppm-send --to 127.0.0.1:5011 --rate 50 --count 10 \
        "{\"ail\": $ail, \"ele\": 1200, \"thr\": 1700, \"rud\": 2000, \"aux12\": 1900}"
done
sleep 0.5
end_ppmd "$cppmd" crsf_ppmd_exit
cat /proc/tty/driver/serial > /out/crsf_proc_serial.txt 2>&1 || true
kill -TERM "$cing"
wait "$cing" || true
echo "pipeline: done"
