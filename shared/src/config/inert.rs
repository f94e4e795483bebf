//! Keys set in the file that do nothing in the configuration they are in:
//! `ppm.frame_us` under follow timing (the default), the follow limits
//! under grid timing, PPM's pulse keys under SBUS, `ppmd.spi_hz` without a
//! PPM `spi:` output, and so on. Taking them silently would let a user
//! believe they act; the program that would use each says so at start,
//! with what governs instead ([`ConfigFile::inert_keys`]). Only keys the file
//! sets are named: a key left at its default is never one the user meant.

use super::merge::ConfigFile;
use super::schema::{Config, OutputSpec, SpinMargin};
use crate::signal::Timing;
use crate::wire::Protocol;

/// The program that would use a key, and so says that it does nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Program {
    /// ppmd: the frame, the line, the real-time settings.
    Ppmd,
    /// udp-ingress: the socket, signing, its state files.
    Ingress,
}

/// A key the file set that does nothing where it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Inert {
    /// The key as the file wrote it (`ppm.frame_us`, `outputs[1].ppm.frame_us`).
    pub key: String,
    /// The program that says so.
    pub by: Program,
    /// Why it does nothing and what governs instead.
    pub why: String,
}

impl std::fmt::Display for Inert {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "config key `{}` is set but does nothing: {}",
            self.key, self.why
        )
    }
}

impl ConfigFile {
    /// The keys this file sets that do nothing in it (each once, naming
    /// the outputs it does nothing for when there are several), for
    /// program `by`. Call it on the configuration the program runs (its
    /// command line applied: `ppmd --timing grid` gives `ppm.frame_us` its
    /// use).
    pub fn inert_keys(&self, by: Program) -> Vec<Inert> {
        let entries = self.entries();
        let several = entries.len() > 1;
        let mut found: Vec<(String, String, Vec<String>)> = Vec::new();
        let mut note = |key: String, why: String, output: Option<&str>| match found
            .iter_mut()
            .find(|(k, w, _)| *k == key && *w == why)
        {
            Some((_, _, outs)) => outs.extend(output.map(str::to_string)),
            None => found.push((key, why, output.map(str::to_string).into_iter().collect())),
        };
        for e in &entries {
            let c = &e.config;
            let name = several.then_some(c.name.as_str());
            for (key, why) in c.inert_output_keys(by) {
                note(c.set.shown(key), why, name);
            }
        }
        if by == Program::Ppmd {
            for (key, why) in self.inert_shared_keys(&entries) {
                note(self.set.shown(key), why, None);
            }
        }
        found
            .into_iter()
            .map(|(key, why, outs)| Inert {
                key,
                by,
                why: match outs.as_slice() {
                    [] => why,
                    [one] => format!("{why} (output `{one}`)"),
                    many => format!(
                        "{why} (outputs {})",
                        many.iter()
                            .map(|n| format!("`{n}`"))
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                },
            })
            .collect()
    }
}

impl Config {
    /// The inert keys of this one output's configuration, for `by`.
    fn inert_output_keys(&self, by: Program) -> Vec<(&'static str, String)> {
        let set = |key: &str| self.set.in_file(key);
        let mut out = Vec::new();
        let ppm = &self.ppm;
        let spec = ppm.protocol.spec();
        match by {
            Program::Ppmd => {
                let module = ppm.protocol == crate::wire::Protocol::Crsf
                    && ppm.crsf_target == crate::wire::crsf::CrsfTarget::Module;
                if !module && set("ppm.crsf_model_id") {
                    out.push((
                        "ppm.crsf_model_id",
                        "it is the model ID ppmd sends a transmitter module, and ppm.crsf_target is not \"module\"".into(),
                    ));
                }
                if module {
                    for key in [
                        "ppm.timing",
                        "ppm.follow_sync_min_us",
                        "ppm.follow_sync_max_us",
                    ] {
                        if set(key) {
                            out.push((
                                key,
                                "under ppm.crsf_target = \"module\" frames follow the module's timing corrections (ppm.frame_us until the first), whatever ppm.timing says".into(),
                            ));
                        }
                    }
                } else if ppm.timing == Timing::Follow && set("ppm.frame_us") {
                    out.push((
                        "ppm.frame_us",
                        format!(
                            "under ppm.timing = \"follow\" (the default) frames follow the commands: a fresh command starts its frame once the {gap} has lasted ppm.follow_sync_min_us, and without one the last frame repeats when it reaches ppm.follow_sync_max_us; for frames every ppm.frame_us set ppm.timing = \"grid\" (or ppmd --timing grid)",
                            gap = spec.gap,
                        ),
                    ));
                }
                if ppm.timing == Timing::Grid && !module {
                    for key in ["ppm.follow_sync_min_us", "ppm.follow_sync_max_us"] {
                        if set(key) {
                            out.push((
                                key,
                                format!(
                                    "under ppm.timing = \"grid\" a frame starts every ppm.frame_us ({} us) whatever the commands do; the follow limits are for ppm.timing = \"follow\"{}",
                                    ppm.frame_us(),
                                    if spec.grid_checks_follow { " (checked against the receiver all the same)" } else { "" }
                                ),
                            ));
                        }
                    }
                }
                for &(key, what) in spec.unused_keys {
                    if set(key) {
                        out.push((
                            key,
                            format!("{what}; the key is PPM's (ppm.protocol = \"ppm\")"),
                        ));
                    }
                }
            }
            Program::Ingress => {
                if set("ingress.seq_file") && self.ingress.auth_key.is_none() {
                    out.push((
                        "ingress.seq_file",
                        "it keeps the last signed seq, and without ingress.auth_key (or udp-ingress --auth-key) commands are not signed: no seq file is kept".into(),
                    ));
                }
                if set("mavlink.timestamp_file") && self.mavlink.key_file.is_none() {
                    out.push((
                        "mavlink.timestamp_file",
                        "it keeps the newest MAVLink signing timestamp, and without mavlink.key_file MAVLink is not signed: no timestamp file is kept".into(),
                    ));
                }
            }
        }
        out
    }

    /// ppmd's shared keys (`[ppmd]`'s sizes and rate, `[rt]`) that none of
    /// the outputs (`entries`) uses.
    fn inert_shared_keys(&self, entries: &[super::OutputEntry]) -> Vec<(&'static str, String)> {
        let set = |key: &str| self.set.in_file(key);
        let outputs: Vec<(OutputSpec, Protocol, bool)> = entries
            .iter()
            .filter_map(|e| {
                let c = &e.config;
                let logs = c.ppmd.frame_log.is_some() || c.ppmd.readback_log.is_some();
                Some((c.output().ok()?, c.ppm.protocol, logs))
            })
            .collect();
        let lines = entries
            .iter()
            .map(|e| format!("`{}`", e.config.ppmd.output))
            .collect::<Vec<_>>()
            .join(", ");
        let mut out = Vec::new();
        let ppm_spi = outputs
            .iter()
            .any(|(o, p, _)| matches!(o, OutputSpec::Spi { .. }) && p.spec().uses_spi_hz);
        if set("ppmd.spi_hz") && !ppm_spi {
            out.push((
                "ppmd.spi_hz",
                format!(
                    "it is the bit rate of a PPM spi: output, and the output is {lines} (SBUS through spi: runs at 100000 Hz whatever it says)"
                ),
            ));
        }
        if set("ppmd.trace_max_mb")
            && !outputs
                .iter()
                .any(|(o, _, _)| matches!(o, OutputSpec::Sim { .. }))
        {
            out.push((
                "ppmd.trace_max_mb",
                format!("it rotates a sim output's trace, and the output is {lines}"),
            ));
        }
        if set("ppmd.frame_log_max_mb") && !outputs.iter().any(|(_, _, log)| *log) {
            out.push((
                "ppmd.frame_log_max_mb",
                "it rotates the frame log and the read-back log, and neither is written (ppmd.frame_log, ppmd --frame-log, ppmd.readback_log)".into(),
            ));
        }
        if !entries.iter().any(|e| e.config.ppmd.readback.is_some()) {
            for key in [
                "readback.tolerance_us",
                "readback.window_ms",
                "readback.frames",
                "readback.idle_level",
                "readback.channels",
            ] {
                if set(key) {
                    out.push((
                        key,
                        "it sets how frames read back are read and judged, and no output has a read-back (ppmd.readback)".into(),
                    ));
                }
            }
        }
        if !entries.iter().any(|e| e.config.ppmd.pilot.is_some()) {
            for key in [
                "pilot.switch_channel",
                "pilot.switch_above_us",
                "pilot.idle_level",
                "pilot.channels",
            ] {
                if set(key) {
                    out.push((
                        key,
                        "it sets how a pilot's radio is read and its takeover switch judged, and no output has one (ppmd.pilot)".into(),
                    ));
                }
            }
        }
        if entries
            .iter()
            .any(|e| e.config.ppmd.readback_log.is_some() && e.config.ppmd.readback.is_none())
            && set("ppmd.readback_log")
        {
            out.push((
                "ppmd.readback_log",
                "it logs the frames read back, and the output has no read-back (ppmd.readback)"
                    .into(),
            ));
        }
        if let SpinMargin::Fixed(us) = self.rt.spin_margin_us {
            for key in ["rt.spin_margin_min_us", "rt.spin_margin_max_us"] {
                if set(key) {
                    out.push((
                        key,
                        format!("rt.spin_margin_us = {us} fixes the margin; the bounds apply to rt.spin_margin_us = \"auto\" only"),
                    ));
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inert(text: &str, by: Program) -> Vec<String> {
        Config::parse(text)
            .unwrap()
            .inert_keys(by)
            .iter()
            .map(|i| i.to_string())
            .collect()
    }

    fn keys(text: &str, by: Program) -> Vec<String> {
        Config::parse(text)
            .unwrap()
            .inert_keys(by)
            .into_iter()
            .map(|i| i.key)
            .collect()
    }

    #[test]
    fn frame_us_under_follow_timing_is_named_with_what_governs() {
        let got = inert("[ppm]\nframe_us = 20000.0", Program::Ppmd);
        assert_eq!(
            got,
            ["config key `ppm.frame_us` is set but does nothing: under ppm.timing = \"follow\" (the default) frames follow the commands: a fresh command starts its frame once the sync has lasted ppm.follow_sync_min_us, and without one the last frame repeats when it reaches ppm.follow_sync_max_us; for frames every ppm.frame_us set ppm.timing = \"grid\" (or ppmd --timing grid)"]
        );
        // udp-ingress has nothing to say of it.
        assert!(inert("[ppm]\nframe_us = 20000.0", Program::Ingress).is_empty());
        // Under grid it is the frame length; left out it is never named.
        assert!(keys(
            "[ppm]\ntiming = \"grid\"\nframe_us = 22500.0",
            Program::Ppmd
        )
        .is_empty());
        assert!(keys("[ppm]\ntiming = \"follow\"", Program::Ppmd).is_empty());
        // The command line's timing counts: --timing grid gives it its use.
        let mut c = Config::parse("[ppm]\nframe_us = 20500.0").unwrap();
        c.ppm.timing = Timing::Grid;
        assert!(c.inert_keys(Program::Ppmd).is_empty());
    }

    #[test]
    fn module_keys_that_the_module_overrides_and_pilot_keys_without_a_pilot_are_named() {
        let k = |t: &str| keys(t, Program::Ppmd);
        let module = "[ppm]\nprotocol = 'crsf'\ncrsf_target = 'module'\n";
        assert_eq!(
            k(&format!("{module}timing = 'follow'\nfollow_sync_max_us = 9000.0\nframe_us = 5000.0\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5")),
            ["ppm.timing", "ppm.follow_sync_max_us"]
        );
        assert_eq!(
            k("[pilot]\nswitch_channel = 5\nswitch_above_us = 1700\nchannels = 8"),
            [
                "pilot.switch_channel",
                "pilot.switch_above_us",
                "pilot.channels"
            ]
        );
        assert!(k("[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5").is_empty());
        assert_eq!(
            k("[ppm]\nprotocol = 'crsf'\ncrsf_model_id = 3"),
            ["ppm.crsf_model_id"]
        );
        assert!(k(&format!(
            "{module}crsf_model_id = 3\n[ppmd]\npilot = 'gpio:GPIO17'\n[pilot]\nswitch_channel = 5"
        ))
        .is_empty());
    }

    #[test]
    fn readback_keys_without_a_readback_are_named() {
        let k = |t: &str| keys(t, Program::Ppmd);
        assert_eq!(
            k("[readback]\ntolerance_us = 20\nframes = 3\n[ppmd]\nreadback_log = 'rb.jsonl'"),
            [
                "readback.tolerance_us",
                "readback.frames",
                "ppmd.readback_log"
            ]
        );
        assert!(k("[readback]\ntolerance_us = 20\n[ppmd]\nreadback = 'gpio:GPIO17'\nreadback_log = 'rb.jsonl'").is_empty());
        // The read-back log is rotated at frame_log_max_mb too.
        assert!(k(
            "[ppmd]\nframe_log_max_mb = 8\nreadback = 'gpio:GPIO17'\nreadback_log = 'rb.jsonl'"
        )
        .is_empty());
    }

    #[test]
    fn keys_of_other_settings_are_named() {
        let k = |t: &str| keys(t, Program::Ppmd);
        assert_eq!(
            k("[ppm]\ntiming = \"grid\"\nfollow_sync_min_us = 6000.0\nfollow_sync_max_us = 9000.0"),
            ["ppm.follow_sync_min_us", "ppm.follow_sync_max_us"]
        );
        assert_eq!(
            k("[ppm]\nprotocol = \"sbus\"\npulse_us = 300.0\nlate_edge_guard_us = 5.0\n[ppmd]\noutput = \"serial:/dev/ttyAMA0\""),
            ["ppm.pulse_us", "ppm.late_edge_guard_us"]
        );
        assert_eq!(
            k("[ppmd]\noutput = \"gpio:GPIO18\"\nspi_hz = 2000000\ntrace_max_mb = 10\nframe_log_max_mb = 8"),
            ["ppmd.spi_hz", "ppmd.trace_max_mb", "ppmd.frame_log_max_mb"]
        );
        // Each where it acts: nothing to say.
        assert!(k("[ppmd]\noutput = \"spi:/dev/spidev0.0\"\nspi_hz = 2000000\nframe_log = \"f.jsonl\"\nframe_log_max_mb = 8").is_empty());
        assert!(k("[ppmd]\ntrace_max_mb = 10").is_empty());
        // SBUS through spi: runs at 100 kHz whatever spi_hz says.
        assert_eq!(
            k("[ppm]\nprotocol = \"sbus\"\n[ppmd]\noutput = \"spi:/dev/spidev0.0\"\nspi_hz = 2000000"),
            ["ppmd.spi_hz"]
        );
        assert_eq!(
            k("[rt]\nspin_margin_us = 50\nspin_margin_min_us = 10\nspin_margin_max_us = 900"),
            ["rt.spin_margin_min_us", "rt.spin_margin_max_us"]
        );
        assert!(k("[rt]\nspin_margin_min_us = 10").is_empty());
        let i = |t: &str| keys(t, Program::Ingress);
        assert_eq!(
            i("[ingress]\nseq_file = \"/var/lib/ppm/s\"\n[mavlink]\ntimestamp_file = \"/var/lib/ppm/t\""),
            ["ingress.seq_file", "mavlink.timestamp_file"]
        );
        assert!(i("[ingress]\nauth_key = \"/k\"\nseq_file = \"/s\"\n[mavlink]\nkey_file = \"/k\"\ntimestamp_file = \"/t\"").is_empty());
        // --auth-key gives the seq file its use.
        let mut c = Config::parse("[ingress]\nseq_file = \"/s\"").unwrap();
        c.ingress.auth_key = Some("/k".into());
        assert!(c.inert_keys(Program::Ingress).is_empty());
    }

    /// With several outputs a key is named as the file wrote it, once,
    /// with the outputs it does nothing for.
    #[test]
    fn output_entries_name_their_keys_and_outputs() {
        let text = "[ppm]\nframe_us = 21000.0\n\n[[outputs]]\nname = \"a\"\noutput = \"sim:a.trace\"\ningress.listen = \"127.0.0.1:5005\"\n\n[[outputs]]\nname = \"b\"\noutput = \"sim:b.trace\"\ningress.listen = \"127.0.0.1:5006\"\n[outputs.ppm]\ntiming = \"follow\"\nfollow_sync_min_us = 6000.0\n\n[[outputs]]\nname = \"c\"\noutput = \"sim:c.trace\"\ningress.listen = \"127.0.0.1:5007\"\n[outputs.ppm]\ntiming = \"grid\"\nframe_us = 22000.0\nfollow_sync_max_us = 9000.0\n";
        let got = Config::parse(text).unwrap().inert_keys(Program::Ppmd);
        let keys: Vec<&str> = got.iter().map(|i| i.key.as_str()).collect();
        assert_eq!(keys, ["ppm.frame_us", "outputs[2].ppm.follow_sync_max_us"]);
        assert!(got[0].why.ends_with(" (outputs `a`, `b`)"), "{}", got[0]);
        assert!(got[1].why.ends_with(" (output `c`)"), "{}", got[1]);
    }

    /// The example configuration and the production one, as shipped, set
    /// no key that does nothing: copied whole, they draw no warning.
    #[test]
    fn the_shipped_configurations_draw_no_warning() {
        for (file, text) in [
            (
                "ppm.example.toml",
                include_str!("../../../ppm.example.toml"),
            ),
            ("deploy/ppm.toml", include_str!("../../../deploy/ppm.toml")),
        ] {
            let c = Config::parse(text).unwrap();
            for by in [Program::Ppmd, Program::Ingress] {
                let inert = c.inert_keys(by);
                assert!(inert.is_empty(), "{file}: {inert:?}");
            }
        }
    }
}
