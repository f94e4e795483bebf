#!/bin/sh
# Bring-up test of the SPI bus (runs inside the VM under busybox sh):
#   tests/vm/run.sh std target/vm/spi-demo-std tests/vm/spi-demo-test.sh
# A gpio-sim chip "ppm-spi" with lines SPI_SCK, SPI_MOSI, SPI_CS, the
# kernel's spi-gpio master on them and spidev bound (spi_gpio_bus), then
# single writes to /dev/spidev0.0 (one transfer each) with the gpio_value
# tracepoint recording the three lines:
#   1. the two bytes 0xa5 0x0f;
#   2. one PPM frame as ppmd's spi output lays it out at 100 kHz (channels
#      1000 1200 1700 2000 1500 1500 1500 1500 us, 300 us pulses: 1220
#      bits, 153 bytes), written three times.
# Output: /out/spi_trace.txt (the trace), /out/spi_lines.txt (global GPIO
# numbers of the lines as the trace shows them, the bit rate, the mode),
# /out/spi_demo.bin (the frame's bytes).
set -eu
. /lib/vmtest.sh

chip=$(make_sim_chip ppm-spi 3 SPI_SCK SPI_MOSI SPI_CS)
base=$(sim_chip_base "$chip")
spidev=$(spi_gpio_bus ppm-spi 0 0 1 2)
echo "spi-demo: $spidev on $chip (base $base)"
grep -A4 "$(basename "$chip")" /sys/kernel/debug/gpio || true
printf 'sck %s\nmosi %s\ncs %s\nhz %s\nmode 0\n' \
    "$base" $((base + 1)) $((base + 2)) 100000 > /out/spi_lines.txt

# The frame's bits, MSB first, as octal escapes for printf.
awk -v hz=100000 -v pulse=300 -v ch="1000 1200 1700 2000 1500 1500 1500 1500" 'BEGIN {
    n = split(ch, c, " "); bits = ""; p = pulse * hz / 1e6
    for (i = 1; i <= n + 1; i++) {
        for (k = 0; k < p; k++) bits = bits "1"
        if (i <= n) for (k = 0; k < (c[i] - pulse) * hz / 1e6; k++) bits = bits "0"
    }
    bits = bits "0"
    while (length(bits) % 8) bits = bits "0"
    for (i = 1; i <= length(bits); i += 8) {
        v = 0
        for (j = 0; j < 8; j++) v = v * 2 + substr(bits, i + j, 1)
        printf "\\%03o", v
    }
}' > /tmp/frame.fmt
# shellcheck disable=SC2059 # the format is the data
printf "$(cat /tmp/frame.fmt)" > /out/spi_demo.bin
size=$(wc -c < /out/spi_demo.bin)
[ "$size" = 153 ] || vmtest_die "frame has $size bytes, want 153"

VMTEST_TRACE_BUF_KB=32768 start_gpio_trace gpio_value
printf '\245\017' | dd of="$spidev" bs=2 count=1 2>/dev/null
for i in 1 2 3; do
    usleep 10000
    dd if=/out/spi_demo.bin of="$spidev" bs=153 count=1 2>/dev/null
done
usleep 10000
stop_gpio_trace /tmp/trace.txt
grep -E "gpio_value: ($base|$((base + 1))|$((base + 2))) " /tmp/trace.txt > /out/spi_trace.txt
echo "spi-demo: $(wc -l < /out/spi_trace.txt) events"
head -n 30 /out/spi_trace.txt
grep -E "gpio_value: $((base + 2)) " /out/spi_trace.txt
echo "spi-demo: OK"
