//! Authenticated commands: a shared 32-byte key, HMAC-SHA256 signatures and
//! the signed envelope.
//!
//! A signed datagram is a JSON object with exactly two strings:
//! `{"msg": "<the command's JSON text>", "mac": "<hex HMAC-SHA256(key, msg)>"}`.
//! The MAC covers the bytes of `msg` (its UTF-8 text once the JSON string is
//! decoded), so the sender signs exactly the text it puts in `msg`. The
//! command in `msg` names the output it is for (`"to": "rover"`, the
//! output's `name`), so what is signed says which vehicle it may fly: a copy
//! sent to another output with the same key is refused ([`Envelope::open`]).
//! The key
//! file holds the key as 64 hex characters and must not be readable or
//! writable by group or others.

use crate::frame::FrameModel;
use crate::protocol::{self, may_have_key, Command, Reject, RejectReason, To};
use hmac::{Hmac, Mac};
use serde_json::Value;
use sha2::Sha256;
use std::path::{Path, PathBuf};

/// Length of the key in bytes.
pub const KEY_LEN: usize = 32;
/// Length of a MAC in hex characters (HMAC-SHA256: 32 bytes).
pub const MAC_HEX_LEN: usize = 64;

type HmacSha256 = Hmac<Sha256>;

/// The shared key. Its `Debug` output does not show it.
#[derive(Clone, PartialEq, Eq)]
pub struct AuthKey([u8; KEY_LEN]);

impl std::fmt::Debug for AuthKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("AuthKey(..)")
    }
}

/// Why a key file was refused. Every variant names the file and says how to
/// fix it.
#[derive(Debug, thiserror::Error)]
pub enum KeyError {
    /// The file cannot be read (missing, no permission, ...; why: its source).
    #[error("cannot read auth key file {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Group or others may read or write the file.
    #[error("auth key file {path} is accessible by group or others (mode {mode:04o}): run `chmod 600 {path}`")]
    Permissions { path: PathBuf, mode: u32 },
    /// The content is not 64 hex characters.
    #[error("auth key file {path} must hold the key as 64 hex characters (32 bytes, e.g. from `openssl rand -hex 32`): {problem}")]
    Format { path: PathBuf, problem: String },
}

impl AuthKey {
    /// A key from its 32 bytes.
    pub fn new(bytes: [u8; KEY_LEN]) -> AuthKey {
        AuthKey(bytes)
    }

    /// A key from 64 hex characters, whitespace around them allowed.
    pub fn from_hex(text: &str) -> Result<AuthKey, String> {
        let t = text.trim();
        if t.len() != 2 * KEY_LEN {
            return Err(format!(
                "found {} characters (whitespace around them aside)",
                t.chars().count()
            ));
        }
        let mut key = [0u8; KEY_LEN];
        hex::decode_to_slice(t, &mut key).map_err(|e| format!("not hex: {e}"))?;
        Ok(AuthKey(key))
    }

    /// Reads a key file: refused when it is not a regular file of at most
    /// [`KEY_MAX_BYTES`](crate::files::KEY_MAX_BYTES), when group or others
    /// may read or write it, when it cannot be read, or when it is not 64 hex
    /// characters.
    pub fn load(path: &Path) -> Result<AuthKey, KeyError> {
        use std::os::unix::fs::PermissionsExt;
        let read = |source| KeyError::Read {
            path: path.to_owned(),
            source,
        };
        let max = crate::files::KEY_MAX_BYTES;
        let file = crate::files::open_regular(std::fs::OpenOptions::new().read(true), path, max)
            .map_err(read)?;
        let mode = file.metadata().map_err(read)?.permissions().mode() & 0o7777;
        if mode & 0o077 != 0 {
            return Err(KeyError::Permissions {
                path: path.to_owned(),
                mode,
            });
        }
        let text = crate::files::read_bounded(&file, max).map_err(read)?;
        AuthKey::from_hex(&text).map_err(|problem| KeyError::Format {
            path: path.to_owned(),
            problem,
        })
    }

    /// The key's bytes (MAVLink 2 signing takes the key itself).
    pub(crate) fn bytes(&self) -> &[u8; KEY_LEN] {
        &self.0
    }

    fn mac(&self) -> HmacSha256 {
        <HmacSha256 as Mac>::new_from_slice(&self.0).expect("HMAC takes any key length")
    }

    /// HMAC-SHA256 of `msg` under this key, lowercase hex.
    pub fn sign(&self, msg: &[u8]) -> String {
        let mut m = self.mac();
        m.update(msg);
        hex::encode(m.finalize().into_bytes())
    }

    /// True when `mac_hex` (64 hex characters, either case) is the MAC of
    /// `msg`. The comparison takes the same time wherever the MACs differ.
    pub fn verify(&self, msg: &[u8], mac_hex: &str) -> bool {
        let mut mac = [0u8; MAC_HEX_LEN / 2];
        if hex::decode_to_slice(mac_hex, &mut mac).is_err() {
            return false;
        }
        let mut m = self.mac();
        m.update(msg);
        m.verify_slice(&mac).is_ok()
    }

    /// The signed datagram carrying `msg`: `{"msg": msg, "mac": sign(msg)}`.
    pub fn envelope(&self, msg: &str) -> String {
        serde_json::json!({"msg": msg, "mac": self.sign(msg.as_bytes())}).to_string()
    }
}

/// A signed datagram, taken apart (not yet verified).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Envelope {
    /// The command's JSON text, as signed.
    pub msg: String,
    /// The MAC as sent, 64 hex characters.
    pub mac: String,
}

impl Envelope {
    /// True when the MAC is `key`'s MAC of `msg`.
    pub fn verify(&self, key: &AuthKey) -> bool {
        key.verify(self.msg.as_bytes(), &self.mac)
    }

    /// The signed command, for the output named `output` (its `name`), in
    /// this order: the MAC must be `key`'s (`bad_mac`); the command must
    /// name this output in `to` (`no_to`, `wrong_output`); it must be a
    /// valid command of `model` (the usual reasons, detail prefixed with
    /// "in the signed msg") and carry a `seq` (`no_seq`). Whether the `seq`
    /// is new is the caller's to judge, after this: a command refused here
    /// leaves the replay state alone.
    pub fn open(&self, key: &AuthKey, output: &str, model: &FrameModel) -> Result<Command, Reject> {
        let fail = |reason, detail: &str| {
            Err(Reject {
                reason,
                detail: detail.into(),
            })
        };
        if !self.verify(key) {
            return fail(
                RejectReason::BadMac,
                "the MAC does not match `msg` (another key, or msg or mac changed)",
            );
        }
        let command = protocol::parse_for(self.msg.as_bytes(), model, To::Exactly(output))
            .map_err(|r| Reject {
                reason: r.reason,
                detail: format!("in the signed msg: {}", r.detail),
            })?;
        if command.seq.is_none() {
            return fail(
                RejectReason::NoSeq,
                "a signed command needs a `seq`, greater than the last one's (replays are refused by it)",
            );
        }
        Ok(command)
    }
}

/// Recognises the signed form, before a datagram is parsed as a command.
///
/// `None`: not a signed datagram (not a JSON object with a `msg` or a `mac`
/// key). `Some(Err(_))`: such an object of the wrong shape (`bad_shape`) or
/// with a MAC that is not 64 hex characters (`bad_mac`). The parsed keys
/// decide, so escaped spellings (`"\u006dsg"`) count; a command that cannot
/// have these keys ([`may_have_key`]) is not parsed twice.
pub fn envelope(datagram: &[u8]) -> Option<Result<Envelope, Reject>> {
    if !may_have_key(datagram, "msg") && !may_have_key(datagram, "mac") {
        return None;
    }
    let Ok(Value::Object(mut map)) = serde_json::from_slice::<Value>(datagram) else {
        return None;
    };
    if !map.contains_key("msg") && !map.contains_key("mac") {
        return None;
    }
    let bad = |reason, detail: String| Some(Err(Reject { reason, detail }));
    if let Some(k) = map.keys().find(|k| *k != "msg" && *k != "mac") {
        return bad(
            RejectReason::BadShape,
            format!("unexpected key `{k}` in a signed datagram: it is {{\"msg\": \"...\", \"mac\": \"...\"}} alone"),
        );
    }
    let (Some(Value::String(msg)), Some(Value::String(mac))) =
        (map.remove("msg"), map.remove("mac"))
    else {
        return bad(
            RejectReason::BadShape,
            "a signed datagram needs `msg` (the command's JSON text) and `mac`, both strings"
                .into(),
        );
    };
    if mac.len() != MAC_HEX_LEN || !mac.bytes().all(|b| b.is_ascii_hexdigit()) {
        return bad(
            RejectReason::BadMac,
            format!("`mac` must be {MAC_HEX_LEN} hex characters (HMAC-SHA256)"),
        );
    }
    Some(Ok(Envelope { msg, mac }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hmac_hex(key: &[u8], msg: &[u8]) -> String {
        let mut m = <HmacSha256 as Mac>::new_from_slice(key).unwrap();
        m.update(msg);
        hex::encode(m.finalize().into_bytes())
    }

    /// RFC 4231, test cases 1 and 2: the HMAC-SHA256 this module uses is the standard one.
    #[test]
    fn rfc4231_vectors() {
        assert_eq!(
            hmac_hex(&[0x0b; 20], b"Hi There"),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7"
        );
        assert_eq!(
            hmac_hex(b"Jefe", b"what do ya want for nothing?"),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }

    fn test_key() -> AuthKey {
        AuthKey::from_hex("000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f")
            .unwrap()
    }

    /// A fixed vector for a 32-byte key (docs/security.md shows the same one).
    #[test]
    fn sign_and_verify_a_fixed_vector() {
        let k = test_key();
        let msg = br#"{"ch":[1500,1500,1000,1500],"seq":1,"to":"rover"}"#;
        // Computed independently with Python's hmac and hashlib.
        let mac = "19eef9dbcc55a46bd2faaba57d00dc42b04194b7b57493491f68d3032314e1fc";
        let got = k.sign(msg);
        assert_eq!(got, mac);
        assert_eq!(got.len(), MAC_HEX_LEN);
        assert!(k.verify(msg, &got));
        assert!(k.verify(msg, &got.to_uppercase()), "hex in either case");
        let mut tampered = got.clone().into_bytes();
        tampered[10] = if tampered[10] == b'0' { b'1' } else { b'0' };
        assert!(!k.verify(msg, std::str::from_utf8(&tampered).unwrap()));
        assert!(!k.verify(
            br#"{"ch":[1500,1500,1001,1500],"seq":1,"to":"rover"}"#,
            &got
        ));
        assert!(
            !k.verify(
                br#"{"ch":[1500,1500,1000,1500],"seq":1,"to":"plane"}"#,
                &got
            ),
            "the output's name is signed"
        );
        assert!(!k.verify(msg, &got[..62]));
        assert!(!k.verify(msg, "zz"));
        let other = AuthKey::new([7; KEY_LEN]);
        assert!(!other.verify(msg, &got));
    }

    #[test]
    fn key_text() {
        let hex64 = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";
        assert_eq!(
            AuthKey::from_hex(&format!("  {}\n", hex64.to_uppercase())).unwrap(),
            test_key()
        );
        assert!(AuthKey::from_hex(&hex64[..62]).unwrap_err().contains("62"));
        assert!(AuthKey::from_hex(&format!("{hex64}00")).is_err());
        assert!(AuthKey::from_hex(&hex64.replace('a', "g"))
            .unwrap_err()
            .contains("not hex"));
        assert!(format!("{:?}", test_key()).contains(".."), "no key in logs");
    }

    #[test]
    fn key_files() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("ppm-auth-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |name: &str, text: &str, mode: u32| {
            let p = dir.join(name);
            std::fs::write(&p, text).unwrap();
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
            p
        };
        let hex64 = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f\n";
        let good = write("good", hex64, 0o600);
        assert_eq!(AuthKey::load(&good).unwrap(), test_key());
        let open = write("open", hex64, 0o644);
        let e = AuthKey::load(&open).unwrap_err().to_string();
        assert!(
            e.contains(&open.display().to_string())
                && e.contains("chmod 600")
                && e.contains("0644"),
            "{e}"
        );
        let e = AuthKey::load(&write("groupw", hex64, 0o620)).unwrap_err();
        assert!(matches!(e, KeyError::Permissions { .. }), "{e}");
        let short = write("short", "abcd", 0o400);
        let e = AuthKey::load(&short).unwrap_err().to_string();
        assert!(
            e.contains(&short.display().to_string()) && e.contains("64 hex"),
            "{e}"
        );
        let missing = dir.join("missing");
        let e = AuthKey::load(&missing).unwrap_err().to_string();
        assert!(e.contains("cannot read") && e.contains("missing"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A key file that is a FIFO, a device or a huge file is refused at
    /// once, and not read whole (a FIFO used to hang the ingress at start).
    #[test]
    fn key_files_that_are_not_small_regular_files_are_refused_at_once() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("ppm-auth-odd-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let fifo = dir.join("fifo");
        nix::unistd::mkfifo(&fifo, nix::sys::stat::Mode::from_bits_truncate(0o600)).unwrap();
        let big = dir.join("big");
        let f = std::fs::File::create(&big).unwrap();
        f.set_len(50 << 20).unwrap();
        f.set_permissions(std::fs::Permissions::from_mode(0o600))
            .unwrap();
        for (path, what) in [
            (fifo, "a FIFO (named pipe), not a regular file"),
            (PathBuf::from("/dev/zero"), "a character device"),
            (
                big,
                "52428800 bytes or more, and this file is never larger than 4096",
            ),
        ] {
            let shown = path.display().to_string();
            let e = crate::files::tests::within_10s(move || AuthKey::load(&path)).unwrap_err();
            let e = crate::logging::Chain(&e).to_string();
            assert!(e.contains(&shown) && e.contains(what), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// What `open` refuses, and why, in its order: the MAC first, then the
    /// output, then the command, then its `seq`.
    #[test]
    fn open_binds_a_signed_command_to_its_output() {
        use RejectReason::*;
        let k = test_key();
        let m = crate::config::Config::default().validate().unwrap();
        let open = |key: &AuthKey, msg: &str, output: &str| {
            let d = key.envelope(msg);
            envelope(d.as_bytes())
                .unwrap()
                .unwrap()
                .open(&k, output, &m)
                .map(|c| (c.seq, c.channels.as_ns()[0]))
                .map_err(|r| r.reason)
        };
        let for_rover = r#"{"ch":[1100],"seq":5,"to":"rover"}"#;
        assert_eq!(open(&k, for_rover, "rover"), Ok((Some(5), 1_100_000)));
        // The same signed command at another output: refused, whatever its seq.
        assert_eq!(open(&k, for_rover, "plane"), Err(WrongOutput));
        assert_eq!(open(&k, r#"{"ch":[1100],"seq":5}"#, "rover"), Err(NoTo));
        assert_eq!(open(&k, "[1100]", "rover"), Err(NoTo));
        assert_eq!(
            open(&k, r#"{"ch":[1100],"seq":5,"to":7}"#, "rover"),
            Err(BadShape)
        );
        // The MAC is checked first: a forgery naming the output is bad_mac.
        let other = AuthKey::new([7; KEY_LEN]);
        assert_eq!(open(&other, for_rover, "rover"), Err(BadMac));
        assert_eq!(open(&other, r#"{"ch":[1100]}"#, "plane"), Err(BadMac));
        // Then the output, then the command and its seq.
        assert_eq!(
            open(&k, r#"{"ch":[9000],"seq":5,"to":"plane"}"#, "rover"),
            Err(WrongOutput)
        );
        assert_eq!(
            open(&k, r#"{"ch":[9000],"seq":5,"to":"rover"}"#, "rover"),
            Err(OutOfRange)
        );
        assert_eq!(
            open(&k, r#"{"ch":[1100],"to":"rover"}"#, "rover"),
            Err(NoSeq)
        );
        let e = envelope(
            k.envelope(r#"{"ch":[1100],"seq":5,"to":"plane"}"#)
                .as_bytes(),
        )
        .unwrap()
        .unwrap()
        .open(&k, "rover", &m)
        .unwrap_err();
        assert_eq!(
            e.detail,
            "in the signed msg: the command is for output `plane`, this is `rover`"
        );
    }

    #[test]
    fn envelopes() {
        let k = test_key();
        let msg = r#"{"ch":[1100],"seq":5}"#;
        let signed = k.envelope(msg);
        let env = envelope(signed.as_bytes()).unwrap().unwrap();
        assert_eq!(env.msg, msg);
        assert!(env.verify(&k));

        for not_signed in [
            &b"[1500]"[..],
            br#"{"ail": 1500}"#,
            br#"{"get":"status"}"#,
            br#"["msg", "mac"]"#,
            br#"{"msg""#,
            b"\xff\"mac\"",
        ] {
            assert_eq!(envelope(not_signed), None, "{not_signed:?}");
        }
        // Escaped keys are the keys they spell (they were taken for a command).
        let escaped = signed
            .replace("\"msg\"", "\"\\u006dsg\"")
            .replace("\"mac\"", "\"m\\u0061c\"");
        assert_ne!(escaped, signed);
        assert_eq!(
            envelope(escaped.as_bytes()),
            Some(Ok(env.clone())),
            "{escaped}"
        );

        let reason = |d: &[u8]| match envelope(d) {
            Some(Err(r)) => r.reason,
            other => panic!("{d:?}: {other:?}"),
        };
        use RejectReason::*;
        let mac = k.sign(msg.as_bytes());
        for (d, want) in [
            (format!(r#"{{"msg": {msg:?}}}"#), BadShape),
            (format!(r#"{{"mac": "{mac}"}}"#), BadShape),
            (format!(r#"{{"msg": 5, "mac": "{mac}"}}"#), BadShape),
            (
                format!(r#"{{"msg": {{"ch":[1100]}}, "mac": "{mac}"}}"#),
                BadShape,
            ),
            (
                format!(r#"{{"msg": {msg:?}, "mac": "{mac}", "seq": 1}}"#),
                BadShape,
            ),
            (format!(r#"{{"msg": {msg:?}, "mac": 1}}"#), BadShape),
            (
                format!(r#"{{"msg": {msg:?}, "mac": "{}"}}"#, &mac[..63]),
                BadMac,
            ),
            (
                format!(r#"{{"msg": {msg:?}, "mac": "{}x"}}"#, &mac[..63]),
                BadMac,
            ),
        ] {
            assert_eq!(reason(d.as_bytes()), want, "{d}");
        }
        // JSON escapes in `msg` are undone before verifying: the MAC is over the text.
        let escaped = format!(r#"{{"mac": "{mac}", "msg": "{{\"ch\":[1100],\u0022seq\":5}}"}}"#);
        assert!(envelope(escaped.as_bytes()).unwrap().unwrap().verify(&k));
    }
}
