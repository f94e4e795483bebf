//! Test helper for the real-kernel tests: prints the terminal settings the
//! kernel holds for a tty (termios2, read through another descriptor while
//! ppmd has the port open), one `key value` a line. Not part of ppm.
//!
//! Usage: tty-settings TTY

fn main() {
    let Some(path) = std::env::args_os().nth(1) else {
        eprintln!("usage: tty-settings TTY");
        std::process::exit(2);
    };
    match ppmd::line::serial::SerialLine::settings_of(std::path::Path::new(&path)) {
        Ok(s) => {
            println!("ispeed {}", s.ispeed);
            println!("ospeed {}", s.ospeed);
            println!("data_bits {}", s.data_bits);
            println!("parity {:?}", s.parity);
            println!("stop_bits {}", s.stop_bits);
            println!("raw {}", s.raw);
            println!("flow_control {}", s.flow_control);
            println!("local_and_read {}", s.local_and_read);
        }
        Err(e) => {
            eprintln!("tty-settings: {}: {e}", path.to_string_lossy());
            std::process::exit(1);
        }
    }
}
