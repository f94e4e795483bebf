//! GPIO lines: one line (or a bank of lines) through the Linux GPIO character device (uAPI v2).
//!
//! [`open`] resolves `gpio:CHIP:LINE` to a chip and a line offset, requests
//! the line as an output (consumer `ppmd`) at the idle level and returns a
//! [`GpioLine`]. Every [`Line::write`] is then one
//! `GPIO_V2_LINE_SET_VALUES` ioctl on the request's file descriptor, with no
//! allocation, logging or lock.
//!
//! CHIP is a path (`/dev/gpiochip0`), a chip name (`gpiochip0`, or just `0`)
//! or a chip label (`pinctrl-bcm2711`, `pinctrl-rp1`, `gpio-sim.0-node0`).
//! LINE is an offset (`18`) or a line name (`GPIO18`).
//!
//! Resolution is split from the system calls: [`find_chip`] and
//! [`find_line`] work on lists of [`ChipSummary`] and line infos, so they are
//! testable without GPIO hardware.

use super::{Bank, Line, LineError};
use gpiocdev::line::{Info as LineInfo, Offset, Value, Values};
use gpiocdev::{Chip, Request};
use nix::errno::Errno;
use ppm_shared::frame::Level;
use ppm_shared::trace::TraceEdge;
use std::fmt;
use std::path::{Path, PathBuf};

/// The consumer label the kernel shows for the requested line (`gpioinfo`).
pub const CONSUMER: &str = "ppmd";

/// How many line names an error message shows at most.
const NAMES_SHOWN: usize = 8;

/// A GPIO line requested as an output. The line is set back to the idle
/// level given to [`open`] when this is dropped.
pub struct GpioLine {
    request: Request,
    idle: Level,
    description: String,
}

impl fmt::Debug for GpioLine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpioLine")
            .field("line", &self.description)
            .field("idle", &self.idle)
            .finish_non_exhaustive()
    }
}

impl GpioLine {
    /// The line and chip, for logs: `GPIO18 (offset 18) on /dev/gpiochip0
    /// (gpiochip0, pinctrl-bcm2711, 58 lines)`.
    pub fn description(&self) -> &str {
        &self.description
    }

    /// The level the line was requested at and returns to on drop.
    pub fn idle_level(&self) -> Level {
        self.idle
    }

    fn set(&self, level: Level) -> Result<(), LineError> {
        self.request
            .set_lone_value(value_of(level))
            .map_err(|e| LineError::Write(write_errno(&e)))
    }
}

impl Line for GpioLine {
    /// One `GPIO_V2_LINE_SET_VALUES` ioctl: gpiocdev's `set_lone_value`
    /// builds the value mask on the stack and neither allocates nor locks.
    fn write(&mut self, edge: &TraceEdge) -> Result<(), LineError> {
        self.set(edge.level)
    }

    fn park(&mut self, level: Level) -> Result<(), LineError> {
        self.set(level)
    }
}

impl Drop for GpioLine {
    fn drop(&mut self) {
        // After release the kernel keeps or resets the line at its driver's
        // whim; the transmitter must see the idle level, so set it first.
        let _ = self.set(self.idle);
    }
}

/// `Level::High` is the physical high: the line is requested active-high.
fn value_of(level: Level) -> Value {
    match level {
        Level::Low => Value::Inactive,
        Level::High => Value::Active,
    }
}

/// The errno of a failed `set_lone_value` (EIO when the error carries
/// none). Never allocates: fit for the timing loop.
fn write_errno(e: &gpiocdev::Error) -> Errno {
    errno_of(e).unwrap_or(Errno::EIO)
}

/// The errno inside a gpiocdev error, if it carries one: an OS error's, or
/// a failed uAPI call's (its `gpiocdev_uapi` error). Never allocates.
fn errno_of(e: &gpiocdev::Error) -> Option<Errno> {
    let n = match e {
        gpiocdev::Error::Os(n) | gpiocdev::Error::Uapi(_, gpiocdev_uapi::Error::Os(n)) => n.0,
        _ => return None,
    };
    // 0: an io::Error that had no OS code.
    (n != 0).then(|| Errno::from_raw(n))
}

/// One GPIO chip as found on the system, for resolving CHIP and for messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChipSummary {
    /// The character device, e.g. `/dev/gpiochip0`.
    pub path: PathBuf,
    /// The kernel's name, e.g. `gpiochip0` (the file name when unreadable).
    pub name: String,
    /// The driver's label, e.g. `pinctrl-bcm2711`; may be empty.
    pub label: String,
    /// How many lines the chip has.
    pub num_lines: u32,
    /// Why the chip could not be opened or queried, if it could not.
    pub unreadable: Option<Errno>,
}

impl fmt::Display for ChipSummary {
    /// `/dev/gpiochip0 (gpiochip0, pinctrl-bcm2711, 58 lines)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let path = self.path.display();
        match self.unreadable {
            Some(e) => write!(f, "{path} ({}, cannot open: {e})", self.name),
            None => {
                let label = if self.label.is_empty() {
                    "no label"
                } else {
                    &self.label
                };
                write!(
                    f,
                    "{path} ({}, {label}, {} lines)",
                    self.name, self.num_lines
                )
            }
        }
    }
}

impl ChipSummary {
    fn of(chip: &Chip) -> Result<ChipSummary, gpiocdev::Error> {
        let info = chip.info()?;
        Ok(ChipSummary {
            path: chip.path().to_owned(),
            name: if info.name.is_empty() {
                chip.name()
            } else {
                info.name
            },
            label: info.label,
            num_lines: info.num_lines,
            unreadable: None,
        })
    }

    fn unreadable(path: &Path, e: &gpiocdev::Error) -> ChipSummary {
        ChipSummary {
            path: path.to_owned(),
            name: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            label: String::new(),
            num_lines: 0,
            unreadable: Some(errno_of(e).unwrap_or(Errno::EIO)),
        }
    }
}

/// Every GPIO chip on the system (`/dev/gpiochip*`), in name order; chips
/// that cannot be opened are listed with their `unreadable` reason set.
pub fn list_chips() -> Vec<ChipSummary> {
    let paths = gpiocdev::chip::chips().unwrap_or_default();
    paths
        .iter()
        .map(|p| {
            Chip::from_path(p)
                .and_then(|c| ChipSummary::of(&c))
                .unwrap_or_else(|e| ChipSummary::unreadable(p, &e))
        })
        .collect()
}

/// The GPIO chips on the system, one per line, or `no GPIO chips found`.
pub fn describe_chips() -> String {
    chip_list(&list_chips())
}

fn chip_list(chips: &[ChipSummary]) -> String {
    if chips.is_empty() {
        return "no GPIO chips found".into();
    }
    chips
        .iter()
        .map(|c| format!("  {c}"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// How CHIP names a chip.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ChipSpec {
    /// A path (starts with `/`), opened directly.
    Path(PathBuf),
    /// A chip name, else a chip label (a bare number `N` means `gpiochipN`).
    NameOrLabel(String),
}

impl ChipSpec {
    /// Parses CHIP.
    pub fn parse(spec: &str) -> ChipSpec {
        if spec.starts_with('/') {
            ChipSpec::Path(spec.into())
        } else if !spec.is_empty() && spec.bytes().all(|b| b.is_ascii_digit()) {
            ChipSpec::NameOrLabel(format!("gpiochip{spec}"))
        } else {
            ChipSpec::NameOrLabel(spec.into())
        }
    }
}

/// How LINE names a line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LineSpec {
    /// A line offset on the chip.
    Offset(Offset),
    /// A line name (`GPIO18`).
    Name(String),
}

impl LineSpec {
    /// Parses LINE: all digits is an offset, anything else a name.
    pub fn parse(spec: &str) -> LineSpec {
        match spec.parse::<Offset>() {
            Ok(o) if spec.bytes().all(|b| b.is_ascii_digit()) => LineSpec::Offset(o),
            _ => LineSpec::Name(spec.into()),
        }
    }
}

/// Picks the chip CHIP names among `chips`: a path matches the path, anything
/// else the chip name first, then the label.
pub fn find_chip<'a>(spec: &str, chips: &'a [ChipSummary]) -> Result<&'a ChipSummary, GpioError> {
    let matches: Vec<&ChipSummary> = match ChipSpec::parse(spec) {
        ChipSpec::Path(p) => chips.iter().filter(|c| c.path == p).collect(),
        ChipSpec::NameOrLabel(n) => {
            let by_name: Vec<_> = chips.iter().filter(|c| c.name == n).collect();
            if by_name.is_empty() {
                chips.iter().filter(|c| c.label == n).collect()
            } else {
                by_name
            }
        }
    };
    match matches.as_slice() {
        [] => Err(GpioError::NoSuchChip {
            chip: spec.into(),
            available: chips.to_vec(),
        }),
        [one] => match one.unreadable {
            Some(errno) => Err(chip_errno_error(one, errno)),
            None => Ok(one),
        },
        many => Err(GpioError::AmbiguousChip {
            chip: spec.into(),
            matches: many.iter().map(|c| (*c).clone()).collect(),
        }),
    }
}

/// Picks the line LINE names among `lines` (the infos of every line of
/// `chip`): an offset must be below the chip's line count; a name matches
/// exactly, else case-insensitively when only one line matches that way.
pub fn find_line<'a>(
    chip: &ChipSummary,
    spec: &str,
    lines: &'a [LineInfo],
) -> Result<&'a LineInfo, GpioError> {
    let found = match LineSpec::parse(spec) {
        LineSpec::Offset(o) => lines.iter().find(|l| l.offset == o),
        LineSpec::Name(n) => lines.iter().find(|l| l.name == n).or_else(|| {
            let mut similar = lines.iter().filter(|l| l.name.eq_ignore_ascii_case(&n));
            match (similar.next(), similar.next()) {
                (Some(l), None) => Some(l),
                _ => None,
            }
        }),
    };
    found.ok_or_else(|| GpioError::NoSuchLine {
        chip: chip_title(chip),
        line: spec.into(),
        num_lines: chip.num_lines,
        names: lines
            .iter()
            .filter(|l| !l.name.is_empty())
            .map(|l| l.name.clone())
            .collect(),
    })
}

/// `gpiochip0 (pinctrl-bcm2711)`, or just the name when there is no label.
fn chip_title(c: &ChipSummary) -> String {
    if c.label.is_empty() || c.label == c.name {
        c.name.clone()
    } else {
        format!("{} ({})", c.name, c.label)
    }
}

/// `GPIO18 (offset 18)`, or `line 18` when the line has no name.
fn line_title(l: &LineInfo) -> String {
    if l.name.is_empty() {
        format!("line {}", l.offset)
    } else {
        format!("{} (offset {})", l.name, l.offset)
    }
}

/// Why the GPIO line could not be had. Every message names the chip (and the
/// line when known) and says how to fix it.
#[derive(Debug, thiserror::Error)]
pub enum GpioError {
    /// CHIP matches no chip on the system.
    #[error("{}", no_such_chip(.chip, .available))]
    NoSuchChip {
        /// CHIP as given.
        chip: String,
        /// Every chip found on the system.
        available: Vec<ChipSummary>,
    },
    /// CHIP matches several chips (a label shared by several chips).
    #[error("GPIO chip `{chip}` matches {} chips; name one by its path or name instead:\n{}", .matches.len(), chip_list(.matches))]
    AmbiguousChip {
        /// CHIP as given.
        chip: String,
        /// The chips it matches.
        matches: Vec<ChipSummary>,
    },
    /// CHIP is a path to something that is not a GPIO character device.
    #[error("`{chip}` is not a GPIO chip ({detail}); CHIP is a /dev/gpiochipN path, a chip name or a chip label. GPIO chips here:\n{}", chip_list(.available))]
    NotAChip {
        /// CHIP as given.
        chip: String,
        /// What is wrong with it.
        detail: String,
        /// Every chip found on the system.
        available: Vec<ChipSummary>,
    },
    /// LINE matches no line of the chip.
    #[error("{}", no_such_line(.chip, .line, *.num_lines, .names))]
    NoSuchLine {
        /// The chip, e.g. `gpiochip0 (pinctrl-bcm2711)`.
        chip: String,
        /// LINE as given.
        line: String,
        /// How many lines the chip has.
        num_lines: u32,
        /// The names of its named lines.
        names: Vec<String>,
    },
    /// No chip has a line of this name (`gpio:LINE`, no CHIP).
    #[error("{}", no_line_anywhere(.line, .chips))]
    NoLineAnywhere {
        /// LINE as given.
        line: String,
        /// Every chip found, with the names of its lines.
        chips: Vec<(ChipSummary, Vec<String>)>,
    },
    /// Several chips have a line of this name (`gpio:LINE`, no CHIP).
    #[error("GPIO line `{line}` is on {} chips; name the chip too, gpio:CHIP:{line}:\n{}", .chips.len(), chip_list(.chips))]
    AmbiguousLine {
        /// LINE as given.
        line: String,
        /// The chips that have it.
        chips: Vec<ChipSummary>,
    },
    /// `gpio:N`: an offset means nothing without its chip.
    #[error("`gpio:{line}`: a line offset needs its chip (gpio:CHIP:{line}); without a chip, name the line (gpio:GPIO18). GPIO chips here:\n{}", chip_list(.available))]
    OffsetWithoutChip {
        /// LINE as given.
        line: String,
        /// Every chip found on the system.
        available: Vec<ChipSummary>,
    },
    /// Someone else holds the line.
    #[error("{}", busy(.chip, .line, .consumer))]
    Busy {
        /// The chip name, e.g. `gpiochip0`.
        chip: String,
        /// The line, e.g. `GPIO18 (offset 18)`.
        line: String,
        /// Who holds it, as the kernel reports it (may be empty).
        consumer: String,
    },
    /// This user may not open the chip.
    #[error("permission denied on {path} (GPIO chip {chip}): add this user to the group that owns it (Raspberry Pi OS: `sudo usermod -aG gpio $USER`, then log in again), or give that group access with a udev rule such as `SUBSYSTEM==\"gpio\", KERNEL==\"gpiochip*\", GROUP=\"gpio\", MODE=\"0660\"` in /etc/udev/rules.d/60-gpio.rules, or run ppmd as root")]
    PermissionDenied {
        /// The chip name.
        chip: String,
        /// The character device.
        path: PathBuf,
    },
    /// The kernel has no GPIO character device with the v2 uAPI.
    #[error("GPIO chip {chip}: the kernel does not support the GPIO character device uAPI v2 ({errno}); ppmd needs Linux >= 5.10 built with CONFIG_GPIO_CDEV=y (CONFIG_GPIO_CDEV_V1 alone is not enough)")]
    NoCdev {
        /// The chip name or path.
        chip: String,
        /// The error the kernel returned.
        errno: Errno,
    },
    /// Any other failure of a GPIO call.
    #[error("GPIO chip {chip}{}: {op} failed: {detail}", line_suffix(.line))]
    Failed {
        /// The chip name or path.
        chip: String,
        /// The line, when known.
        line: Option<String>,
        /// What was being done.
        op: &'static str,
        /// The error, as gpiocdev reports it.
        detail: String,
    },
}

fn no_such_chip(chip: &str, available: &[ChipSummary]) -> String {
    if available.is_empty() {
        format!(
            "no GPIO chip `{chip}`: no GPIO chips found (no /dev/gpiochip*): this board has no GPIO driver loaded or the kernel lacks the GPIO character device (needs CONFIG_GPIO_CDEV); without GPIO hardware use sim (--output sim; for a read-back, readback = \"sim:PATH\")"
        )
    } else {
        format!(
            "no GPIO chip `{chip}`; CHIP is a /dev/gpiochipN path, a chip name or a chip label. GPIO chips here:\n{}",
            chip_list(available)
        )
    }
}

fn no_line_anywhere(line: &str, chips: &[(ChipSummary, Vec<String>)]) -> String {
    if chips.is_empty() {
        return format!(
            "no GPIO line `{line}`: no GPIO chips found (no /dev/gpiochip*): this board has no GPIO driver loaded or the kernel lacks the GPIO character device (needs CONFIG_GPIO_CDEV); set ppmd.output (or ppmd.readback) to this board's line (gpio:CHIP:LINE), or sim without GPIO hardware"
        );
    }
    let each: Vec<String> = chips
        .iter()
        .map(|(c, names)| {
            let more = if names.len() > NAMES_SHOWN {
                ", ..."
            } else {
                ""
            };
            let shown: Vec<&str> = names.iter().take(NAMES_SHOWN).map(|s| s.as_str()).collect();
            if names.is_empty() {
                format!("  {c}: lines without names")
            } else {
                format!("  {c}: {}{more}", shown.join(", "))
            }
        })
        .collect();
    format!(
        "no GPIO chip here has a line named `{line}` (a Raspberry Pi 4 or 5 has GPIO18 on pinctrl-bcm2711 or pinctrl-rp1): set ppmd.output (or ppmd.readback) to this board's line, gpio:CHIP:LINE or gpio:LINE with one of these names (`gpioinfo` lists them all):\n{}",
        each.join("\n")
    )
}

/// The chip that has the line named `line`, for `gpio:LINE` without a
/// chip: the one chip among `chips` (each with its lines' infos) with a
/// line of exactly that name, or else the one with it in another case.
pub fn chip_with_line<'a>(
    line: &str,
    chips: &'a [(ChipSummary, Vec<LineInfo>)],
) -> Result<&'a ChipSummary, GpioError> {
    if let LineSpec::Offset(_) = LineSpec::parse(line) {
        return Err(GpioError::OffsetWithoutChip {
            line: line.into(),
            available: chips.iter().map(|c| c.0.clone()).collect(),
        });
    }
    let with = |exact: bool| -> Vec<&'a ChipSummary> {
        chips
            .iter()
            .filter(|(_, lines)| {
                lines.iter().any(|l| {
                    if exact {
                        l.name == line
                    } else {
                        l.name.eq_ignore_ascii_case(line)
                    }
                })
            })
            .map(|(c, _)| c)
            .collect()
    };
    let mut found = with(true);
    if found.is_empty() {
        found = with(false);
    }
    match found.as_slice() {
        [one] => Ok(one),
        [] => Err(GpioError::NoLineAnywhere {
            line: line.into(),
            chips: chips
                .iter()
                .map(|(c, lines)| {
                    let names = lines
                        .iter()
                        .filter(|l| !l.name.is_empty())
                        .map(|l| l.name.clone())
                        .collect();
                    (c.clone(), names)
                })
                .collect(),
        }),
        many => Err(GpioError::AmbiguousLine {
            line: line.into(),
            chips: many.iter().map(|c| (*c).clone()).collect(),
        }),
    }
}

/// The path of the chip that has the line named `line` on this system (see
/// [`chip_with_line`]); chips that cannot be read are passed over.
pub fn find_chip_with_line(line: &str) -> Result<PathBuf, GpioError> {
    let chips: Vec<(ChipSummary, Vec<LineInfo>)> = list_chips()
        .into_iter()
        .filter(|c| c.unreadable.is_none())
        .filter_map(|c| {
            let chip = Chip::from_path(&c.path).ok()?;
            let lines = chip
                .line_info_iter()
                .and_then(|it| it.collect::<Result<Vec<_>, _>>())
                .ok()?;
            Some((c, lines))
        })
        .collect();
    Ok(chip_with_line(line, &chips)?.path.clone())
}

fn no_such_line(chip: &str, line: &str, num_lines: u32, names: &[String]) -> String {
    let range = match num_lines {
        0 => "no lines".to_string(),
        1 => "1 line (offset 0)".to_string(),
        n => format!("{n} lines (offsets 0..={})", n - 1),
    };
    let named = if names.is_empty() {
        "its lines have no names, so give an offset".to_string()
    } else {
        let more = if names.len() > NAMES_SHOWN {
            ", ..."
        } else {
            ""
        };
        let shown: Vec<&str> = names.iter().take(NAMES_SHOWN).map(|s| s.as_str()).collect();
        format!("line names: {}{more}", shown.join(", "))
    };
    format!(
        "no line `{line}` on GPIO chip {chip}: it has {range}; LINE is an offset or a line name ({named}; `gpioinfo` lists them all)"
    )
}

fn busy(chip: &str, line: &str, consumer: &str) -> String {
    if consumer.is_empty() {
        format!(
            "{line} on {chip} is in use by the kernel (another driver or a pin function holds it): remove the dtoverlay or driver that claims the pin, or pick another line"
        )
    } else {
        format!(
            "{line} on {chip} is in use by `{consumer}`: stop that program or remove the dtoverlay/driver that claims the pin (`gpioinfo {chip}` shows the holders), or pick another line"
        )
    }
}

fn line_suffix(line: &Option<String>) -> String {
    match line {
        Some(l) => format!(", {l}"),
        None => String::new(),
    }
}

/// The error for an errno met while opening or querying `chip`.
fn chip_errno_error(chip: &ChipSummary, errno: Errno) -> GpioError {
    match errno {
        Errno::EACCES | Errno::EPERM => GpioError::PermissionDenied {
            chip: chip.name.clone(),
            path: chip.path.clone(),
        },
        Errno::ENOTTY | Errno::EINVAL => GpioError::NoCdev {
            chip: chip.name.clone(),
            errno,
        },
        _ => GpioError::Failed {
            chip: chip.path.display().to_string(),
            line: None,
            op: "opening the chip",
            detail: errno.to_string(),
        },
    }
}

/// Maps a gpiocdev error met while opening or querying `chip` to a
/// [`GpioError`]: permission and missing-uAPI errors get their own variants.
fn chip_error(chip: &ChipSummary, op: &'static str, e: &gpiocdev::Error) -> GpioError {
    match errno_of(e) {
        Some(n @ (Errno::EACCES | Errno::EPERM | Errno::ENOTTY | Errno::EINVAL)) => {
            chip_errno_error(chip, n)
        }
        _ => GpioError::Failed {
            chip: chip.name.clone(),
            line: None,
            op,
            detail: e.to_string(),
        },
    }
}

/// Opens the chip CHIP names.
fn open_chip(spec: &str) -> Result<(Chip, ChipSummary), GpioError> {
    let summary = match ChipSpec::parse(spec) {
        ChipSpec::Path(path) => {
            let chip = Chip::from_path(&path).map_err(|e| path_error(spec, &path, &e))?;
            let summary = ChipSummary::of(&chip).map_err(|e| {
                chip_error(&ChipSummary::unreadable(&path, &e), "reading chip info", &e)
            })?;
            return Ok((chip, summary));
        }
        ChipSpec::NameOrLabel(_) => find_chip(spec, &list_chips())?.clone(),
    };
    let chip =
        Chip::from_path(&summary.path).map_err(|e| chip_error(&summary, "opening the chip", &e))?;
    Ok((chip, summary))
}

fn path_error(spec: &str, path: &Path, e: &gpiocdev::Error) -> GpioError {
    match e {
        gpiocdev::Error::GpioChip(_, kind) => GpioError::NotAChip {
            chip: spec.into(),
            detail: kind.to_string(),
            available: list_chips(),
        },
        _ => match errno_of(e) {
            Some(Errno::ENOENT | Errno::ENOTDIR) => GpioError::NoSuchChip {
                chip: spec.into(),
                available: list_chips(),
            },
            Some(n) => chip_errno_error(&ChipSummary::unreadable(path, e), n),
            None => GpioError::Failed {
                chip: spec.into(),
                line: None,
                op: "opening the chip",
                detail: e.to_string(),
            },
        },
    }
}

/// Opens `gpio:CHIP:LINE`: resolves the chip and the line, and requests the
/// line as an output with consumer `ppmd`, initially at `idle`.
///
/// CHIP is a path (`/dev/gpiochip0`), a chip name (`gpiochip0` or `0`) or a
/// chip label (`pinctrl-bcm2711`); LINE is an offset (`18`) or a line name
/// (`GPIO18`).
pub fn open(chip: &str, line: &str, idle: Level) -> Result<GpioLine, GpioError> {
    let (handle, summary, info) = resolve_line(chip, line)?;
    let offset = info.offset;
    let title = line_title(&info);
    let request = Request::builder()
        .on_chip(&summary.path)
        .with_consumer(CONSUMER)
        .with_line(offset)
        .as_active_high()
        .as_output(value_of(idle))
        .request()
        .map_err(|e| request_error(&handle, &summary, std::slice::from_ref(&info), &e))?;
    Ok(GpioLine {
        request,
        idle,
        description: format!("{title} on {summary}"),
    })
}

/// Several lines of one GPIO chip in one request: the lines of several
/// outputs, written together when their edges are due at the same time. Every
/// [`Bank::write`] is one `GPIO_V2_LINE_SET_VALUES` ioctl; the value set is
/// kept with room for every line, so updating it never allocates. Each line
/// is set back to its idle level when this is dropped.
pub struct GpioBank {
    request: Request,
    offsets: Vec<Offset>,
    idle: Vec<Level>,
    values: Values,
    descriptions: Vec<String>,
}

impl fmt::Debug for GpioBank {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpioBank")
            .field("lines", &self.descriptions)
            .finish_non_exhaustive()
    }
}

impl GpioBank {
    /// Each line and its chip, for logs, in the order given to [`open_bank`].
    pub fn descriptions(&self) -> &[String] {
        &self.descriptions
    }

    /// Sets the value set to `mask`'s lines at `levels` and writes it.
    fn set(&mut self, mask: u64, levels: u64) -> Result<(), LineError> {
        fill_values(&mut self.values, &self.offsets, mask, levels);
        self.request
            .set_values(&self.values)
            .map_err(|e| LineError::Write(write_errno(&e)))
    }
}

impl Bank for GpioBank {
    fn write(&mut self, _scheduled_ns: u64, mask: u64, levels: u64) -> Result<(), LineError> {
        self.set(mask, levels)
    }

    fn park(&mut self, bit: u32, level: Level) -> Result<(), LineError> {
        self.set(1 << bit, (level == Level::High) as u64 * (1 << bit))
    }
}

impl Drop for GpioBank {
    fn drop(&mut self) {
        let levels = self
            .idle
            .iter()
            .enumerate()
            .fold(0, |acc, (i, l)| acc | ((*l == Level::High) as u64) << i);
        let _ = self.set((1 << self.offsets.len()) - 1, levels);
    }
}

/// Makes `values` hold exactly the lines of `offsets` in `mask` (bit `i` is
/// `offsets[i]`), each at its bit in `levels`. Never allocates once `values`
/// has held every line (as [`open_bank`] leaves it): removing and inserting
/// keep the capacity.
pub fn fill_values(values: &mut Values, offsets: &[Offset], mask: u64, levels: u64) {
    for (i, &offset) in offsets.iter().enumerate() {
        if mask & (1 << i) == 0 {
            values.unset(offset);
        } else {
            let high = levels & (1 << i) != 0;
            values.set(offset, value_of(Level::from_bit(high)));
        }
    }
}

/// Opens several lines of one chip as outputs in one request (consumer
/// `ppmd`), each initially at its idle level: `lines` holds each line's LINE
/// (an offset or a name) and idle level. Line `i` of the bank is `lines[i]`.
pub fn open_bank(chip: &str, lines: &[(String, Level)]) -> Result<GpioBank, GpioError> {
    assert!((1..=64).contains(&lines.len()), "1..=64 lines");
    let (handle, summary, infos) = chip_lines(chip)?;
    let mut found: Vec<LineInfo> = Vec::new();
    for (line, _) in lines {
        let info = find_line(&summary, line, &infos)?.clone();
        if let Some(prev) = found.iter().find(|i| i.offset == info.offset) {
            return Err(GpioError::Failed {
                chip: summary.name.clone(),
                line: Some(line_title(&info)),
                op: "requesting the lines",
                detail: format!(
                    "two outputs name the same line (`{line}` is {})",
                    line_title(prev)
                ),
            });
        }
        found.push(info);
    }
    let mut builder = Request::builder();
    builder.on_chip(&summary.path).with_consumer(CONSUMER);
    for (info, (_, idle)) in found.iter().zip(lines) {
        builder
            .with_line(info.offset)
            .as_active_high()
            .as_output(value_of(*idle));
    }
    let request = builder
        .request()
        .map_err(|e| request_error(&handle, &summary, &found, &e))?;
    let offsets: Vec<Offset> = found.iter().map(|i| i.offset).collect();
    let mut values = Values::from_offsets(&offsets);
    for o in &offsets {
        values.unset(*o);
    }
    Ok(GpioBank {
        request,
        idle: lines.iter().map(|(_, l)| *l).collect(),
        descriptions: found
            .iter()
            .map(|i| format!("{} on {summary}", line_title(i)))
            .collect(),
        offsets,
        values,
    })
}

/// Finds the chip CHIP and its line LINE (as [`open`] does; an empty CHIP:
/// the chip that has a line named LINE, [`find_chip_with_line`]), for
/// tools that request the line themselves; returns the open chip, its
/// summary and the line's info.
pub fn resolve_line(chip: &str, line: &str) -> Result<(Chip, ChipSummary, LineInfo), GpioError> {
    let found;
    let chip = if chip.is_empty() {
        found = find_chip_with_line(line)?;
        found.to_str().unwrap_or_default()
    } else {
        chip
    };
    let (handle, summary, lines) = chip_lines(chip)?;
    let info = find_line(&summary, line, &lines)?.clone();
    Ok((handle, summary, info))
}

/// Opens the chip CHIP names and reads the info of every line.
fn chip_lines(chip: &str) -> Result<(Chip, ChipSummary, Vec<LineInfo>), GpioError> {
    let (handle, summary) = open_chip(chip)?;
    let lines = handle
        .line_info_iter()
        .and_then(|it| it.collect::<Result<Vec<_>, _>>())
        .map_err(|e| chip_error(&summary, "reading line info", &e))?;
    Ok((handle, summary, lines))
}

/// The error for a failed request of `lines` (as outputs) on `chip`: busy
/// names the line held and its holder; permission and missing-uAPI errors
/// get their own variants.
fn request_error(
    handle: &Chip,
    summary: &ChipSummary,
    lines: &[LineInfo],
    e: &gpiocdev::Error,
) -> GpioError {
    let titles = || lines.iter().map(line_title).collect::<Vec<_>>().join(", ");
    match errno_of(e) {
        Some(Errno::EBUSY) => {
            let held = lines.iter().find_map(|i| {
                let now = handle.line_info(i.offset).ok()?;
                now.used.then(|| (line_title(i), now.consumer))
            });
            let (line, consumer) = held.unwrap_or_else(|| (titles(), String::new()));
            GpioError::Busy {
                chip: summary.name.clone(),
                line,
                consumer,
            }
        }
        Some(Errno::EACCES | Errno::EPERM | Errno::ENOTTY) => chip_error(summary, "", e),
        _ => GpioError::Failed {
            chip: summary.name.clone(),
            line: Some(titles()),
            op: if lines.len() == 1 {
                "requesting the line as an output"
            } else {
                "requesting the lines as outputs"
            },
            detail: e.to_string(),
        },
    }
}

/// The error for a failed request of `line` as an input (the read-back's,
/// [`crate::input`]): as for an output, a busy line names its holder and
/// permission and missing-uAPI errors get their own variants.
pub(crate) fn input_request_error(
    handle: &Chip,
    summary: &ChipSummary,
    line: &LineInfo,
    e: &gpiocdev::Error,
) -> GpioError {
    match request_error(handle, summary, std::slice::from_ref(line), e) {
        GpioError::Failed {
            chip, line, detail, ..
        } => GpioError::Failed {
            chip,
            line,
            op: "requesting the line as an input",
            detail,
        },
        other => other,
    }
}

/// `NAME (offset N)` or `offset N` for messages.
pub fn describe_line(info: &LineInfo) -> String {
    line_title(info)
}

#[cfg(test)]
mod tests;
