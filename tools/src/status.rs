//! Status queries: ask a udp-ingress (`{"get": "status"}`) and print its
//! reply readably. Used by `ppm-status` and `ppm-send --status`.

use anyhow::{bail, Context, Result};
use ppm_shared::protocol::RejectReason;
use ppm_shared::status::{PpmdStatus, StatusReply};
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::time::Duration;

/// Resolves `HOST:PORT` to its first address.
pub fn resolve(to: &str) -> Result<SocketAddr> {
    to.to_socket_addrs()
        .with_context(|| format!("resolving {to}"))?
        .next()
        .with_context(|| format!("{to} resolves to no address"))
}

/// Sends one status query to `to` and returns the reply's text, or says
/// why there is none within `timeout`.
pub fn query(to: SocketAddr, timeout: Duration) -> Result<String> {
    if timeout.is_zero() {
        bail!("--timeout must be longer than 0");
    }
    let bind: SocketAddr = if to.is_ipv4() { "0.0.0.0:0" } else { "[::]:0" }.parse()?;
    let socket = UdpSocket::bind(bind).context("opening a UDP socket")?;
    // Connected: only `to`'s reply is taken, and "nothing listens there" is reported.
    socket
        .connect(to)
        .with_context(|| format!("addressing {to}"))?;
    socket.set_read_timeout(Some(timeout))?;
    // Padded: no reply is more than 3 times its query (unless the source is
    // in ingress.status_allow), so a bare 16-byte query may get only
    // {"pad_to": N}.
    socket
        .send(&ppm_shared::protocol::padded_status_query())
        .with_context(|| format!("sending to {to}"))?;
    let mut buf = vec![0u8; 65_536];
    let n = match socket.recv(&mut buf) {
        Ok(n) => n,
        Err(e)
            if matches!(
                e.kind(),
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
            ) =>
        {
            bail!(
                "no reply from {to} within {timeout:?}: is udp-ingress running and listening there (ingress.listen)? A firewall, or an ingress.allow without this machine, may also drop the datagrams"
            )
        }
        Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {
            bail!("{to} refused the query (port unreachable): nothing listens there; is udp-ingress running, with this ingress.listen?")
        }
        Err(e) => return Err(e).with_context(|| format!("waiting for the reply from {to}")),
    };
    Ok(String::from_utf8_lossy(&buf[..n]).into_owned())
}

/// Parses the text of a status reply from `from`: an error says whether it
/// is not JSON at all or not the reply's shape.
pub fn parse(text: &str, from: SocketAddr) -> Result<StatusReply> {
    let v: serde_json::Value = serde_json::from_str(text)
        .with_context(|| format!("the reply from {from} is not JSON: {text}"))?;
    serde_json::from_value(v).with_context(|| format!("unexpected reply: {text}"))
}

/// A status reply as a few lines of text.
pub fn readable(r: &StatusReply) -> String {
    let d = &r.datagrams;
    // In the protocol's order, then any reason this tool does not know.
    let known = RejectReason::ALL.map(|r| r.as_str());
    let rejected = &d.rejected.0;
    let order = known
        .iter()
        .copied()
        .filter(|k| rejected.contains_key(*k))
        .chain(
            rejected
                .keys()
                .map(String::as_str)
                .filter(|k| !known.contains(k)),
        );
    let reasons: Vec<String> = order
        .filter_map(|reason| match rejected[reason] {
            0 => None,
            n => Some(format!("{reason} {n}")),
        })
        .collect();
    let rejected_total = d.rejected.total();
    let mut out = format!("udp-ingress `{}`, up {}\n", r.name, uptime(r.uptime_s));
    // Replies from before the receive thread's settings were reported lack it.
    if let Some(t) = &r.receiver {
        out += &format!(
            "receive thread: {}, {}, {}{}\n",
            t.wait,
            match t.priority {
                p if p > 0 => format!("SCHED_FIFO {p}"),
                _ => "SCHED_OTHER".to_string(),
            },
            t.cpu.map_or("any CPU".to_string(), |c| format!("CPU {c}")),
            if t.degraded { " (DEGRADED RUN)" } else { "" },
        );
    }
    out += &format!(
        "datagrams: received {}, applied {}, superseded {}, stale {}{}, clamped {} ({} values)\n",
        d.received,
        d.applied,
        d.superseded,
        d.stale,
        match d.seq_resets {
            n if n > 0 => format!(" (seq gate reset {n}x)"),
            _ => String::new(),
        },
        d.clamped,
        d.clamped_values,
    );
    out += &if reasons.is_empty() {
        format!("rejected: {rejected_total}\n")
    } else {
        format!("rejected: {rejected_total} ({})\n", reasons.join(", "))
    };
    out += &match r.newest_command_age_ms {
        None => "newest command: none yet\n".to_string(),
        Some(ms) => format!(
            "newest command: {} ago{}\n",
            age(ms),
            r.newest_seq
                .map(|s| format!(", seq {s}"))
                .unwrap_or_default()
        ),
    };
    out += &format!(
        "status queries: {} ({} replies dropped)\n",
        r.status_requests, r.status_dropped
    );
    out += &match &r.ppmd {
        None if r.ppmd_stale => {
            "ppmd: no timing snapshot for more than 3 s (stopped, or hanging?)\n".to_string()
        }
        None => {
            "ppmd: no timing snapshot yet (not running, or another name or ipc.root?)\n".to_string()
        }
        Some(p) => ppmd_line(p),
    };
    if let Some(rb) = &r.readback {
        out += &format!(
            "read-back of {}: {} ({} changes), {} frames read, {} not ppm's\n",
            rb.input, rb.state, rb.changes, rb.frames, rb.mismatched
        );
    }
    if let Some(t) = &r.telemetry {
        out += &telemetry_line(t);
    }
    out
}

/// The `telemetry ...` line of [`readable`]: the flight controller's
/// state, then each kind it sent, then the frames.
fn telemetry_line(t: &ppm_shared::crsf::report::TelemetryStatus) -> String {
    let mut parts = vec![t.state.clone()];
    if let Some(b) = &t.battery {
        parts.push(format!(
            "battery {:.1} V {:.1} A {} mAh {} %",
            b.voltage_v, b.current_a, b.used_mah, b.remaining_pct
        ));
    }
    if let Some(a) = &t.attitude {
        parts.push(format!(
            "roll {:.1} pitch {:.1} yaw {:.1} deg",
            a.roll_rad.to_degrees(),
            a.pitch_rad.to_degrees(),
            a.yaw_rad.to_degrees()
        ));
    }
    if let Some(g) = &t.gps {
        parts.push(format!(
            "GPS {:.7} {:.7} {} m {} satellites",
            g.lat_deg, g.lon_deg, g.altitude_m, g.satellites
        ));
    }
    if let Some(f) = &t.flight_mode {
        parts.push(format!("mode {}", f.mode));
    }
    let bad: u64 = t.bad.values().sum();
    format!(
        "telemetry on {}: {}; {} frames, {bad} bad\n",
        t.port,
        parts.join(", "),
        t.frames
    )
}

/// The `ppmd: ...` line of [`readable`].
fn ppmd_line(p: &PpmdStatus) -> String {
    let e = &p.edge_error_us;
    format!(
        "ppmd: {}{}, {} frames{}; edge error p50 {:.2} us, p99 {:.2} us, max {:.1} us; {} overruns, {} late frames, {} aborted frames, {} glitched frames, {} failsafe entries{} (snapshot {} old)\n",
        p.state,
        if p.degraded { " (DEGRADED RUN)" } else { "" },
        p.frames,
        match p.timing.as_str() {
            "follow" => format!(" (follow timing, {} repeats)", p.repeats),
            _ => String::new(),
        },
        e.p50,
        e.p99,
        e.max,
        p.overruns,
        p.late_frames,
        p.aborted_frames,
        p.glitched_frames,
        p.failsafe_entries,
        [
            match p.mismatched_commands {
                n if n > 0 => {
                    format!("; {n} commands REFUSED: udp-ingress runs with another channel model")
                }
                _ => String::new(),
            },
            match p.log_errors {
                n if n > 0 => format!("; {n} log rows or intervals not written"),
                _ => String::new(),
            },
        ]
        .concat(),
        age(p.snapshot_age_ms),
    )
}

/// `3d 04h 05m 06s`, `5m 06s`, `6.2s`.
fn uptime(s: f64) -> String {
    let whole = s as u64;
    let (d, h, m, sec) = (
        whole / 86_400,
        whole / 3_600 % 24,
        whole / 60 % 60,
        whole % 60,
    );
    if d > 0 {
        format!("{d}d {h:02}h {m:02}m {sec:02}s")
    } else if h > 0 {
        format!("{h}h {m:02}m {sec:02}s")
    } else if m > 0 {
        format!("{m}m {sec:02}s")
    } else {
        format!("{s:.1}s")
    }
}

/// `12.3 ms`, `4.2 s`, `3m 20s`.
fn age(ms: f64) -> String {
    if ms < 1_000.0 {
        format!("{ms:.1} ms")
    } else if ms < 60_000.0 {
        format!("{:.1} s", ms / 1e3)
    } else {
        uptime(ms / 1e3)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::Value;

    /// The reply `r`, sent as text, parsed and made readable.
    fn read(r: &Value) -> String {
        readable(&parse(&r.to_string(), ([127, 0, 0, 1], 9).into()).unwrap())
    }

    #[test]
    fn readable_reply() {
        let r: Value = serde_json::from_str(
            r#"{"name":"ppm","uptime_s":3725.5,
            "receiver":{"wait":"epoll","policy":"fifo","priority":70,"cpu":null,"degraded":true},
            "datagrams":{"received":12,"applied":9,
            "rejected":{"invalid_utf8":0,"invalid_json":2,"not_a_number":0,"out_of_range":0,
            "too_many_values":0,"unknown_channel":0,"bad_shape":1},"clamped":1,"clamped_values":2,
            "stale":0,"seq_resets":2,"superseded":0},"status_requests":4,"status_dropped":0,
            "newest_command_age_ms":12.34,"newest_seq":41,
            "ppmd":{"state":"active","frames":5000,"edge_error_us":{"p50":0.031,"p99":0.05,"max":12.4},
            "overruns":0,"late_frames":1,"aborted_frames":3,"glitched_frames":1,"failsafe_entries":2,"degraded":true,"snapshot_age_ms":420.0},
            "ppmd_stale":false}"#,
        )
        .unwrap();
        assert_eq!(
            read(&r),
            "udp-ingress `ppm`, up 1h 02m 05s\n\
             receive thread: epoll, SCHED_FIFO 70, any CPU (DEGRADED RUN)\n\
             datagrams: received 12, applied 9, superseded 0, stale 0 (seq gate reset 2x), clamped 1 (2 values)\n\
             rejected: 3 (invalid_json 2, bad_shape 1)\n\
             newest command: 12.3 ms ago, seq 41\n\
             status queries: 4 (0 replies dropped)\n\
             ppmd: active (DEGRADED RUN), 5000 frames; edge error p50 0.03 us, p99 0.05 us, max 12.4 us; 0 overruns, 1 late frames, 3 aborted frames, 1 glitched frames, 2 failsafe entries (snapshot 420.0 ms old)\n"
        );
        let mut r = r;
        r["ppmd"] = Value::Null;
        r["ppmd_stale"] = Value::Bool(true);
        r["newest_command_age_ms"] = Value::Null;
        r["receiver"]["wait"] = "busy_poll".into();
        r["receiver"]["priority"] = 0.into();
        r["receiver"]["cpu"] = 1.into();
        r["receiver"]["degraded"] = false.into();
        let text = read(&r);
        assert!(
            text.contains("receive thread: busy_poll, SCHED_OTHER, CPU 1\n"),
            "{text}"
        );
        assert!(text.contains("newest command: none yet"), "{text}");
        assert!(text.contains("more than 3 s"), "{text}");
        r["telemetry"] = serde_json::json!({"state": "receiving", "port": "/dev/ttyAMA0",
            "age_ms": 2.0, "frames": 160, "bad": {"bad_crc": 40, "truncated": 1},
            "junk_bytes": 0, "other": 0,
            "battery": {"voltage_v": 16.8, "current_a": 12.3, "used_mah": 1234,
                "remaining_pct": 75, "age_ms": 1.0},
            "attitude": {"roll_rad": -0.5, "pitch_rad": 0.1234, "yaw_rad": 3.0, "age_ms": 1.0},
            "gps": null, "flight_mode": {"mode": "ANGL", "age_ms": 1.0}, "vario": null,
            "baro_altitude": null, "link_statistics": null});
        let text = read(&r);
        assert!(
            text.ends_with("telemetry on /dev/ttyAMA0: receiving, battery 16.8 V 12.3 A 1234 mAh 75 %, roll -28.6 pitch 7.1 yaw 171.9 deg, mode ANGL; 160 frames, 41 bad\n"),
            "{text}"
        );
        r["datagrams"] = Value::Null;
        assert!(parse(&r.to_string(), ([127, 0, 0, 1], 9).into()).is_err());
    }

    #[test]
    fn durations() {
        assert_eq!(uptime(6.25), "6.2s");
        assert_eq!(uptime(306.0), "5m 06s");
        assert_eq!(
            uptime(3.0 * 86_400.0 + 4.0 * 3_600.0 + 5.0 * 60.0 + 6.0),
            "3d 04h 05m 06s"
        );
        assert_eq!(age(4_200.0), "4.2 s");
        assert_eq!(age(200_000.0), "3m 20s");
    }
}
