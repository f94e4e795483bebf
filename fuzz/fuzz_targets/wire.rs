//! Raw datagram bytes through the wire protocol parser, against every model.
//!
//! On acceptance: every channel within its limits, one value per channel, the
//! encoded frame well-formed (2*(n+1) edges in order, at least 4 ms of sync)
//! and decoded back exactly. On rejection: a counted reason. The input is also
//! split at newlines into a stream of datagrams that goes through `SeqGate`
//! like udp-ingress does, checked against a reference.
//!
//! The signed form too: the bytes go through `auth::envelope` (a signed
//! datagram whose MAC verifies under the README's test key has its `msg`
//! parsed like a plain command, and opened for the vector's output, which it
//! must name in `to`), and the bytes as text are signed, taken apart again
//! and verified.
#![no_main]

use libfuzzer_sys::fuzz_target;
use ppm_fuzz::{check_envelope, check_open, check_signing, models, parse_checked};
use ppm_shared::protocol::SeqGate;

fuzz_target!(|data: &[u8]| {
    let signed_msg = check_envelope(data);
    if let Ok(text) = std::str::from_utf8(data) {
        check_signing(text);
    }
    for m in models() {
        if let Some(msg) = &signed_msg {
            let _ = parse_checked(msg.as_bytes(), m);
        }
        check_open(data, m);
        let whole = parse_checked(data, m);

        // The same datagram twice through a fresh gate: the first passes, a
        // repeat passes only without a seq.
        if let Ok(cmd) = &whole {
            let mut g = SeqGate::default();
            assert!(g.admit(cmd.seq));
            assert_eq!(g.admit(cmd.seq), cmd.seq.is_none());
        }

        // A stream of datagrams (one per line) through one gate.
        if data.contains(&b'\n') {
            let mut gate = SeqGate::default();
            let mut last: Option<u64> = None;
            for datagram in data.split(|&b| b == b'\n') {
                let Ok(cmd) = parse_checked(datagram, m) else {
                    continue;
                };
                let want = match (cmd.seq, last) {
                    (None, _) => true,
                    (Some(s), Some(l)) => s > l,
                    (Some(_), None) => true,
                };
                assert_eq!(
                    gate.admit(cmd.seq),
                    want,
                    "seq {:?} after {last:?}",
                    cmd.seq
                );
                if want && cmd.seq.is_some() {
                    last = cmd.seq;
                }
            }
        }
    }
});
