//! Configuration text through `Config::parse` and `Config::validate`: never a
//! panic, every error names a key or the file, and every model that validates
//! satisfies what transmitters need (1..=16 channels, 4..19 ms of sync,
//! pulse shorter than every channel's minimum, frames decoded back exactly).
#![no_main]

use libfuzzer_sys::fuzz_target;
use ppm_fuzz::check_model;
use ppm_shared::config::{Config, ConfigError};
use ppm_shared::frame::Protocol;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let config = match Config::parse(text) {
        Ok(c) => c,
        Err(e) => {
            assert!(matches!(e, ConfigError::Parse { .. }), "{e:?}");
            let _ = e.to_string();
            return;
        }
    };
    match config.validate() {
        Ok(m) => {
            check_model(&m);
            assert_eq!(m.channels(), config.ppm.channels() as usize);
            // SBUS's idle level depends on the output when not given.
            if config.ppm.idle_level.is_some() || m.protocol() == Protocol::Ppm {
                assert_eq!(m.idle_level(), config.ppm.idle_level());
            }
        }
        Err(e) => {
            let key = e
                .key()
                .expect("a validation error names its key")
                .to_string();
            assert!(!key.is_empty());
            assert!(e.to_string().contains(&key), "{e}");
        }
    }
});
