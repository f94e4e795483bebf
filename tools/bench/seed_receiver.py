#!/usr/bin/env python3
"""Baseline for ppm-bench: a command receiver written the way the seed
system's was. A blocking UDP socket, json.loads on every datagram, and each
command handed to a separate generator process through a multiprocessing
pipe (the seed's generator drove pigpio waves; here it only receives).

It measures what ppm-bench measures for udp-ingress: from the kernel's
receive timestamp of each datagram (SO_TIMESTAMPNS, CLOCK_REALTIME) to the
moment its command has been handed over. On SIGTERM (or after --count
datagrams) it prints one JSON object: count, received, p50_us, p99_us,
max_us, and exits.

Usage: seed_receiver.py PORT [--count N]
"""
import json
import multiprocessing
import signal
import socket
import struct
import sys
import time

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


def generator(conn):
    while True:
        cmd = conn.recv()
        if cmd is None:
            return


def percentile(sorted_values, q):
    if not sorted_values:
        return 0.0
    rank = max(1, min(len(sorted_values), int(-(-q * len(sorted_values) // 1))))
    return sorted_values[rank - 1]


def main():
    port = int(sys.argv[1])
    count = int(sys.argv[sys.argv.index("--count") + 1]) if "--count" in sys.argv else 0
    parent, child = multiprocessing.Pipe()
    gen = multiprocessing.Process(target=generator, args=(child,), daemon=True)
    gen.start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind(("127.0.0.1", port))
    latencies = []
    received = 0
    stop = [False]

    def on_term(*_):
        stop[0] = True
        sock.close()

    signal.signal(signal.SIGTERM, on_term)
    print("ready", flush=True)
    while not stop[0] and (count == 0 or received < count):
        try:
            data, anc, _flags, _addr = sock.recvmsg(65536, socket.CMSG_SPACE(16))
        except OSError:
            break
        received += 1
        kernel_ns = None
        for level, kind, payload in anc:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                sec, nsec = struct.unpack("qq", payload[:16])
                kernel_ns = sec * 1_000_000_000 + nsec
        try:
            cmd = json.loads(data)
        except ValueError:
            continue
        parent.send(cmd)
        if kernel_ns is not None:
            latencies.append((time.clock_gettime_ns(time.CLOCK_REALTIME) - kernel_ns) / 1000.0)
    parent.send(None)
    latencies.sort()
    print(json.dumps({
        "count": len(latencies),
        "received": received,
        "p50_us": percentile(latencies, 0.5),
        "p99_us": percentile(latencies, 0.99),
        "max_us": latencies[-1] if latencies else 0.0,
    }), flush=True)


if __name__ == "__main__":
    main()
