//! Which keys a configuration file set, and how a message names each: as
//! written in the file (`ppm.frame_us`, `outputs[1].frame_log`), or as the
//! command-line option that gave its value (`--auth-key`). The programs
//! warn about keys set in the file that do nothing where they are
//! ([`inert`](super::inert)), and name the key in the errors they meet
//! using the files and devices the keys name ([`fault`](super::fault)).

/// The keys a file set (dotted, as [`ConfigError`](super::ConfigError)
/// names them, with how the file wrote each), and the keys whose value a
/// command-line option gave.
///
/// Not part of the settings: two configurations with the same settings
/// are equal however they were written, so `==` ignores it.
#[derive(Debug, Clone, Default)]
pub struct SetKeys {
    /// (key, as written): `("ppm.frame_us", "outputs[1].ppm.frame_us")`.
    file: Vec<(String, String)>,
    /// (key, option): `("ingress.auth_key", "--auth-key")`.
    options: Vec<(String, &'static str)>,
}

impl PartialEq for SetKeys {
    fn eq(&self, _: &SetKeys) -> bool {
        true
    }
}

/// How a message names the key a value came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum KeyName {
    /// The configuration file's key, as written there (or its own name
    /// when the file left it at its default).
    File(String),
    /// The command-line option that gave the value.
    Option(&'static str),
}

impl KeyName {
    /// The key's or the option's name.
    pub fn as_str(&self) -> &str {
        match self {
            KeyName::File(k) => k,
            KeyName::Option(o) => o,
        }
    }

    /// Whether the value came from the command line.
    pub fn is_option(&self) -> bool {
        matches!(self, KeyName::Option(_))
    }
}

impl SetKeys {
    /// Notes `key` as set in the file, written there as `written`
    /// (replacing what an inherited key said).
    pub(crate) fn note(&mut self, key: impl Into<String>, written: impl Into<String>) {
        let key = key.into();
        let written = written.into();
        match self.file.iter_mut().find(|(k, _)| *k == key) {
            Some(slot) => slot.1 = written,
            None => self.file.push((key, written)),
        }
    }

    /// Notes that command-line `option` gave `key`'s value.
    pub fn note_option(&mut self, key: &str, option: &'static str) {
        self.options.retain(|(k, _)| k != key);
        self.options.push((key.to_string(), option));
    }

    /// Whether the file set `key` (a command-line option aside).
    pub fn in_file(&self, key: &str) -> bool {
        self.file.iter().any(|(k, _)| k == key)
    }

    /// The keys the file set, as written there.
    pub fn written(&self) -> impl Iterator<Item = &str> {
        self.file.iter().map(|(_, w)| w.as_str())
    }

    /// How a message names `key`: the option that gave its value, or the
    /// key as the file wrote it (its own name when the file left it out).
    pub fn name(&self, key: &str) -> KeyName {
        if let Some((_, o)) = self.options.iter().find(|(k, _)| k == key) {
            return KeyName::Option(o);
        }
        KeyName::File(
            self.file
                .iter()
                .find(|(k, _)| k == key)
                .map_or_else(|| key.to_string(), |(_, w)| w.clone()),
        )
    }

    /// [`SetKeys::name`] as text.
    pub fn shown(&self, key: &str) -> String {
        self.name(key).as_str().to_string()
    }
}
