//! The `[[outputs]]` entries: each is laid over the top-level sections into
//! a whole configuration, the file as that output sees it, and remembers
//! which keys it set itself, so an error met in it names the key where it
//! was written (`outputs[1].ppm.channels`, or the top-level key it
//! inherited).

use super::schema::Config;
use super::ConfigError;
use std::path::PathBuf;

/// A configuration file as parsed: its top-level sections (`config`: the
/// one output a file without `[[outputs]]` describes, and what every entry
/// inherits) and its `[[outputs]]` entries, each a whole [`Config`] of its
/// own. A [`Config`] is one output's sections and holds no outputs; the
/// file's shared keys (`rt`, `ipc`, ...) are read from `config` (which it
/// dereferences to).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ConfigFile {
    /// The top-level sections.
    pub config: Config,
    /// `[[outputs]]`: several outputs driven by one ppmd (see
    /// [`OutputEntry`]). Empty when the file has no `[[outputs]]`: it then
    /// describes one output, `config`.
    pub outputs: Vec<OutputEntry>,
}

impl From<Config> for ConfigFile {
    /// A file of one output, `config`.
    fn from(config: Config) -> ConfigFile {
        ConfigFile {
            config,
            outputs: Vec::new(),
        }
    }
}

impl std::ops::Deref for ConfigFile {
    type Target = Config;
    fn deref(&self) -> &Config {
        &self.config
    }
}

impl std::ops::DerefMut for ConfigFile {
    fn deref_mut(&mut self) -> &mut Config {
        &mut self.config
    }
}

/// One output of a configuration with several: an `[[outputs]]` entry, or
/// one made on ppmd's command line (`--output NAME=SPEC`).
#[derive(Debug, Clone, PartialEq)]
pub struct OutputEntry {
    /// The top-level sections with the entry's keys laid over them.
    pub config: Config,
    origin: Origin,
}

/// Where an output's keys were written, to name them in its errors.
#[derive(Debug, Clone, PartialEq)]
enum Origin {
    /// The file has no `[[outputs]]`: it is this output, its keys are its own.
    Whole,
    /// An `[[outputs]]` entry: the keys it sets itself (dotted, as in error
    /// messages); the others it inherits from the top level.
    Entry(Vec<String>),
    /// Made by ppmd's `--output NAME=SPEC`: no keys of its own in the file.
    CommandLine,
}

impl OutputEntry {
    /// Whether the output has its own `[[outputs]]` entry in the file (its
    /// own udp-ingress settings).
    pub(crate) fn in_file(&self) -> bool {
        matches!(self.origin, Origin::Entry(_))
    }

    /// `e` as met while checking this output, the `i`th: a key the entry
    /// sets is named `outputs[i].KEY`; an inherited one keeps its top-level
    /// name and says which output it failed for.
    pub(crate) fn locate(&self, i: usize, e: ConfigError) -> ConfigError {
        let keys = match &self.origin {
            Origin::Whole => return e,
            Origin::Entry(keys) => keys.as_slice(),
            Origin::CommandLine => &[],
        };
        match e {
            ConfigError::Invalid { key, message }
                if self.origin == Origin::CommandLine && key == "ppmd.output" =>
            {
                let c = &self.config;
                ConfigError::Usage(format!("--output {}={}: {message}", c.name, c.ppmd.output))
            }
            ConfigError::Invalid { key, message } => {
                let own = keys.iter().any(|k| {
                    k == &key
                        || k.starts_with(&format!("{key}."))
                        || key.starts_with(&format!("{k}."))
                });
                if own {
                    ConfigError::Invalid {
                        key: entry_key(i, &key),
                        message,
                    }
                } else if !["ppm.", "ingress.", "failsafe."]
                    .iter()
                    .any(|p| key.starts_with(p))
                {
                    ConfigError::Invalid { key, message }
                } else {
                    let name = &self.config.name;
                    ConfigError::Invalid {
                        key,
                        message: format!("{message} (inherited by output `{name}`, outputs[{i}])"),
                    }
                }
            }
            other => other,
        }
    }
}

impl Config {
    /// Parses configuration text (see [`Config::load`]): the top-level
    /// sections, and each `[[outputs]]` entry laid over them.
    pub fn parse(text: &str) -> Result<ConfigFile, ConfigError> {
        let parse_error = |message: String| ConfigError::Parse {
            path: PathBuf::from("<text>"),
            message: message.trim_end().replace('\n', " | "),
        };
        let mut table: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        let entries = match table.remove("outputs") {
            None => Vec::new(),
            Some(toml::Value::Array(a)) => a,
            Some(_) => {
                return Err(parse_error(
                    "`outputs` must be an array of tables: write each output as [[outputs]]".into(),
                ))
            }
        };
        let mut cfg: Config = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e: toml::de::Error| parse_error(e.to_string()))?;
        for (k, v) in &table {
            let mut keys = Vec::new();
            collect_keys(k, v, &mut keys);
            for key in keys {
                cfg.set.note(key.clone(), key);
            }
        }
        if entries.is_empty() {
            return Ok(cfg.into());
        }
        let mut file = ConfigFile::from(cfg);
        for key in [
            "name",
            "ppmd.output",
            "ppmd.frame_log",
            "ppmd.readback",
            "ppmd.readback_log",
            "ppmd.pilot",
        ] {
            if lookup(&table, key).is_some() {
                return Err(ConfigError::invalid(
                    key,
                    "with [[outputs]] every output sets its own `name`, `output`, `frame_log`, `readback`, `readback_log` and `pilot` in its entry; remove the top-level key",
                ));
            }
        }
        for (i, entry) in entries.into_iter().enumerate() {
            let toml::Value::Table(entry) = entry else {
                return Err(parse_error(format!("outputs[{i}] must be a table")));
            };
            let mut merged = table.clone();
            let mut keys = Vec::new();
            for (k, v) in entry {
                match k.as_str() {
                    "name" => {
                        keys.push("name".into());
                        merged.insert(k, v);
                    }
                    "output" | "frame_log" | "readback" | "readback_log" | "pilot" => {
                        keys.push(format!("ppmd.{k}"));
                        let ppmd = merged
                            .entry("ppmd")
                            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                        if let toml::Value::Table(t) = ppmd {
                            t.insert(k, v);
                        }
                    }
                    "ppm" | "ingress" | "failsafe" | "mavlink" => {
                        collect_keys(&k, &v, &mut keys);
                        let base = merged
                            .entry(k.as_str())
                            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                        overlay(base, v);
                    }
                    _ => {
                        return Err(parse_error(format!(
                            "outputs[{i}]: unknown key `{k}`; an output entry takes name, output, frame_log, readback, readback_log, pilot and the sections [outputs.ppm], [outputs.ingress], [outputs.failsafe] and [outputs.mavlink] (rt, ipc, readback, pilot, frame_log_max_mb, trace_max_mb and spi_hz are shared: set them at the top level)"
                        )))
                    }
                }
            }
            if !keys.iter().any(|k| k == "name") {
                return Err(ConfigError::invalid(
                    format!("outputs[{i}].name"),
                    "every output needs a name (udp-ingress --name NAME picks it)",
                ));
            }
            let mut out: Config = toml::Value::Table(merged)
                .try_into()
                .map_err(|e: toml::de::Error| parse_error(format!("outputs[{i}]: {e}")))?;
            out.set = file.set.clone();
            for key in &keys {
                out.set.note(key.clone(), entry_key(i, key));
            }
            file.outputs.push(OutputEntry {
                config: out,
                origin: Origin::Entry(keys),
            });
        }
        Ok(file)
    }
}

impl ConfigFile {
    /// The outputs this configuration describes: its `[[outputs]]` entries,
    /// or the configuration itself when it has none.
    pub fn entries(&self) -> Vec<OutputEntry> {
        if self.outputs.is_empty() {
            vec![OutputEntry {
                config: self.config.clone(),
                origin: Origin::Whole,
            }]
        } else {
            self.outputs.clone()
        }
    }

    /// The names of the outputs, for messages.
    pub fn output_names(&self) -> Vec<String> {
        self.entries().into_iter().map(|e| e.config.name).collect()
    }

    /// The one output a single-output program (udp-ingress, a tool) works
    /// with: `name` picks an `[[outputs]]` entry (required when there are
    /// several); without entries, `name` renames the file's one output.
    pub fn select(&self, name: Option<&str>) -> Result<Config, ConfigError> {
        if self.outputs.is_empty() {
            let mut c = self.config.clone();
            if let Some(n) = name {
                c.name = n.to_string();
            }
            return Ok(c);
        }
        match name {
            None => match self.outputs.as_slice() {
                [only] => Ok(only.config.clone()),
                _ => Err(ConfigError::Usage(format!(
                    "the configuration has {} outputs ({}): pick one with --name NAME",
                    self.outputs.len(),
                    self.output_names().join(", ")
                ))),
            },
            Some(n) => self
                .outputs
                .iter()
                .find(|e| e.config.name == n)
                .map(|e| e.config.clone())
                .ok_or_else(|| {
                    ConfigError::Usage(format!(
                        "no output `{n}` in the configuration's [[outputs]]; its outputs: {}",
                        self.output_names().join(", ")
                    ))
                }),
        }
    }

    /// Adds an output made on ppmd's command line (`--output NAME=SPEC`):
    /// it has no keys of its own in the file, so its errors name the
    /// command-line argument.
    pub fn push_cli_output(&mut self, output: Config) {
        self.outputs.push(OutputEntry {
            config: output,
            origin: Origin::CommandLine,
        });
    }
}

/// Key `key` as entry `i` of `[[outputs]]` writes it: `outputs[1].ppm.channels`,
/// and `outputs[1].output` for `ppmd.output` (likewise `frame_log`).
fn entry_key(i: usize, key: &str) -> String {
    let shown = key
        .strip_prefix("ppmd.")
        .filter(|k| *k == "output" || *k == "frame_log")
        .unwrap_or(key);
    format!("outputs[{i}].{shown}")
}

/// Most outputs one ppmd drives.
pub const MAX_OUTPUTS: usize = 8;

/// The value at a dotted key path in a TOML table.
fn lookup<'a>(table: &'a toml::Table, dotted: &str) -> Option<&'a toml::Value> {
    let mut parts = dotted.split('.');
    let mut v = table.get(parts.next()?)?;
    for p in parts {
        v = v.as_table()?.get(p)?;
    }
    Some(v)
}

/// Every leaf key under `prefix` in `v`, dotted.
fn collect_keys(prefix: &str, v: &toml::Value, out: &mut Vec<String>) {
    match v {
        toml::Value::Table(t) => {
            for (k, v) in t {
                collect_keys(&format!("{prefix}.{k}"), v, out);
            }
        }
        _ => out.push(prefix.to_string()),
    }
}

/// Lays `top` over `base`: tables merge key by key, anything else replaces.
fn overlay(base: &mut toml::Value, top: toml::Value) {
    match (base, top) {
        (toml::Value::Table(b), toml::Value::Table(t)) => {
            for (k, v) in t {
                match b.get_mut(&k) {
                    Some(slot) => overlay(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}
