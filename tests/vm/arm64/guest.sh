#!/bin/bash
# tests/vm/arm64/guest.sh: the package's whole-system test inside the
# Debian arm64 guest (tests/tests/vm_arm64.rs), run as root by the image's
# test-runner unit once systemd has the system up. /mnt/out is the host's
# share: the package (ppm_VERSION-1_arm64.deb and its next revision) comes
# in; results go out.
#   1. a gpio-sim chip named and labelled like a Raspberry Pi 4's
#      (pinctrl-bcm2711, lines GPIO0 to GPIO27), then `apt-get install
#      ./ppm_..._arm64.deb` with nothing edited; the services must come up;
#   2. writes `ready` and waits for the host's `sent`: the host sends its
#      commands to udp-ingress from outside, through QEMU's user network,
#      while the gpio_value tracepoint records GPIO18 (trace.txt and
#      trace_raw.txt, the same events with nanosecond times);
#   3. the journal's warnings since the install (journal_warnings.txt) and
#      `systemd-analyze security` of both units (security_*.txt);
#   4. SIGSTOP to ppmd: the watchdog must have it restarted;
#   5. an edited /etc/ppm/ppm.toml, then the package's next revision
#      (the host's ppm_VERSION-2_arm64.deb, the same package): the edit
#      stays and the services restart;
#   6. `apt-get remove` stops the services; `apt-get purge` removes
#      /etc/ppm and /var/log/ppm.
# With a file `short` in the share it stops after 4: the steps after it do
# not depend on the kernel, and the host runs them in one boot only.
# Every check that fails here stops the script with "FAIL: ..." in
# guest.log; what the host checks is in results.txt (KEY=VALUE lines).
set -euo pipefail
OUT=/mnt/out
# At the end, pass or fail: what the boot logged, and what failed.
# shellcheck disable=SC2317 # called through the trap
finish() {
    local status=$?
    journalctl -b -o short-monotonic --no-pager > "$OUT/boot_journal.txt" 2>&1 || true
    systemctl --failed --no-legend --plain > "$OUT/failed.txt" 2>&1 || true
    echo "$status" > "$OUT/status"
}
trap finish EXIT
cd /tmp

step() { echo "== [$(cut -d' ' -f1 /proc/uptime) s] $*"; }
fail() { echo "FAIL: $*"; exit 1; }
result() { echo "$1=$2" >> "$OUT/results.txt"; }
: > "$OUT/results.txt"
UNITS=(ppmd.service udp-ingress.service)
# wait_for SECONDS COMMAND...: runs COMMAND every 0.2 s until it succeeds.
wait_for() {
    local until=$((SECONDS + $1)); shift
    until "$@" >/dev/null 2>&1; do
        [ $SECONDS -lt "$until" ] || return 1
        sleep 0.2
    done
}
active() { systemctl is-active --quiet "$@"; }
main_pid() { systemctl show -p MainPID --value "$1"; }

step "system $(systemctl is-system-running --wait || true), kernel $(uname -r)"
result kernel "$(uname -r)"
result system "$(systemctl is-system-running)"

step "gpio-sim chip pinctrl-bcm2711 with GPIO0..GPIO27"
insmod "/opt/ppm-vmtest/$(uname -r)/irq_sim.ko"
insmod "/opt/ppm-vmtest/$(uname -r)/gpio-sim.ko"
sim=/sys/kernel/config/gpio-sim/pi
mkdir "$sim" "$sim/bank0"
echo pinctrl-bcm2711 > "$sim/bank0/label"
echo 28 > "$sim/bank0/num_lines"
for i in $(seq 0 27); do
    mkdir "$sim/bank0/line$i"
    echo "GPIO$i" > "$sim/bank0/line$i/name"
done
echo 1 > "$sim/live"
chip=$(cat "$sim/bank0/chip_name")
wait_for 10 test -c "/dev/$chip" || fail "/dev/$chip did not appear"
# The global number of GPIO18, as the tracepoint names it.
dev=$(readlink -f "/sys/bus/gpio/devices/$chip")
base=$(cat "${dev%/*}"/gpio/gpiochip*/base)
result gpio18 $((base + 18))

step "tracing gpio_value"
T=/sys/kernel/tracing
echo 0 > $T/tracing_on
echo 16384 > $T/buffer_size_kb
echo mono > $T/trace_clock
echo > $T/trace
echo 1 > $T/events/gpio/gpio_value/enable
echo 1 > $T/tracing_on

cursor=$(journalctl -n 0 --show-cursor | sed -n 's/^-- cursor: //p')
# The package, and the same as its next revision (VERSION-1, VERSION-2),
# copied where apt's unprivileged download user can read them.
debs=("$OUT"/ppm_*_arm64.deb)
[ ${#debs[@]} = 2 ] || fail "want two packages in the share, not: ${debs[*]}"
cp "${debs[@]}" /tmp/
chmod 644 /tmp/ppm_*_arm64.deb
deb=/tmp/${debs[0]##*/} next_deb=/tmp/${debs[1]##*/}
step "apt-get install ./${deb##*/}"
DEBIAN_FRONTEND=noninteractive apt-get install -y "$deb" > "$OUT/install.log" 2>&1 ||
    { cat "$OUT/install.log"; fail "apt-get install failed"; }
version=$(dpkg-query -W -f='${Version}' ppm)
result version "$version"
wait_for 60 active "${UNITS[@]}" ||
    { systemctl status --no-pager "${UNITS[@]}" || true; fail "the services did not come up"; }
for u in "${UNITS[@]}"; do result "enabled_${u%.service}" "$(systemctl is-enabled "$u")"; done
result user_groups "$(id -nG ppm | tr ' ' ,)"
result chip_group "$(stat -c %G "/dev/$chip")"

ip -br addr > "$OUT/ip.txt"
step "ready: the host sends its commands"
touch "$OUT/ready"
wait_for 300 test -e "$OUT/sent" || fail "the host sent nothing"
# Past the failsafe (200 ms), the line is silent.
sleep 1
ppm-status --to 127.0.0.1:5005 --timeout 5s > "$OUT/ppm_status.txt" 2>&1 || true
echo 0 > $T/tracing_on
cat $T/trace > "$OUT/trace.txt"
echo 1 > $T/options/raw
cat $T/trace > "$OUT/trace_raw.txt"
echo 0 > $T/options/raw
echo 0 > $T/events/gpio/gpio_value/enable
active "${UNITS[@]}" || fail "a service stopped while commands came"

step "journal and sandboxes"
journalctl -p warning --after-cursor="$cursor" --no-pager -q -o short-monotonic \
    > "$OUT/journal_warnings.txt" || true
journalctl --after-cursor="$cursor" --no-pager -q -o short-monotonic > "$OUT/journal.txt" || true
for u in "${UNITS[@]}"; do
    systemd-analyze security --no-pager "$u" > "$OUT/security_${u%.service}.txt" 2>&1 || true
    result "exposure_${u%.service}" \
        "$(sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p' "$OUT/security_${u%.service}.txt")"
done

step "a frozen ppmd"
before=$(main_pid ppmd.service)
restarts=$(systemctl show -p NRestarts --value ppmd.service)
kill -STOP "$before"
restarted() { active ppmd.service && [ "$(main_pid ppmd.service)" != "$before" ] && [ "$(main_pid ppmd.service)" != 0 ]; }
wait_for 60 restarted || fail "ppmd, stopped, was not restarted"
result watchdog_restarts "$(($(systemctl show -p NRestarts --value ppmd.service) - restarts))"
result watchdog_result "$(journalctl -u ppmd.service --no-pager -q -o cat | grep -c 'Watchdog timeout' || true)"

if [ -e "$OUT/short" ]; then
    step "done (short)"
    exit 0
fi

step "an upgrade over an edited configuration"
sed -i 's/^after_ms = 200$/after_ms = 250/' /etc/ppm/ppm.toml
grep -qx 'after_ms = 250' /etc/ppm/ppm.toml || fail "could not edit /etc/ppm/ppm.toml"
pids="$(main_pid ppmd.service) $(main_pid udp-ingress.service)"
DEBIAN_FRONTEND=noninteractive apt-get install -y "$next_deb" > "$OUT/upgrade.log" 2>&1 ||
    { cat "$OUT/upgrade.log"; fail "the upgrade failed"; }
wait_for 60 active "${UNITS[@]}" || fail "the services did not come back after the upgrade"
result upgraded_version "$(dpkg-query -W -f='${Version}' ppm)"
result upgraded_keeps_edit "$(grep -cx 'after_ms = 250' /etc/ppm/ppm.toml || true)"
result upgraded_pids_before "$pids"
result upgraded_pids_after "$(main_pid ppmd.service) $(main_pid udp-ingress.service)"

step "remove, purge"
DEBIAN_FRONTEND=noninteractive apt-get remove -y ppm > "$OUT/remove.log" 2>&1 ||
    { cat "$OUT/remove.log"; fail "apt-get remove failed"; }
result removed_states "$(systemctl is-active "${UNITS[@]}" | tr '\n' ' ' || true)"
result removed_keeps_config "$(test -f /etc/ppm/ppm.toml && echo yes || echo no)"
DEBIAN_FRONTEND=noninteractive apt-get purge -y ppm > "$OUT/purge.log" 2>&1 ||
    { cat "$OUT/purge.log"; fail "apt-get purge failed"; }
result purged_config "$(test -e /etc/ppm && echo present || echo gone)"
result purged_logs "$(test -e /var/log/ppm && echo present || echo gone)"
result purged_package "$(dpkg-query -W -f='${db:Status-Abbrev}' ppm 2>/dev/null || echo none)"
step done
