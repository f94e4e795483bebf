//! The GPIO output: one line through the Linux GPIO character device (uAPI v2).
//!
//! [`open`] resolves `gpio:CHIP:LINE` to a chip and a line offset, requests
//! the line as an output (consumer `ppmd`) at the idle level and returns a
//! [`GpioOutput`]. Every [`Output::write`] is then one
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

use super::{Bank, Output, OutputError};
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
pub struct GpioOutput {
    request: Request,
    idle: Level,
    description: String,
}

impl fmt::Debug for GpioOutput {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpioOutput")
            .field("line", &self.description)
            .field("idle", &self.idle)
            .finish_non_exhaustive()
    }
}

impl GpioOutput {
    /// The line and chip, for logs: `GPIO18 (offset 18) on /dev/gpiochip0
    /// (gpiochip0, pinctrl-bcm2711, 58 lines)`.
    pub fn description(&self) -> &str {
        &self.description
    }

    /// The level the line was requested at and returns to on drop.
    pub fn idle_level(&self) -> Level {
        self.idle
    }

    fn set(&self, level: Level) -> Result<(), OutputError> {
        self.request
            .set_lone_value(value_of(level))
            .map_err(|e| OutputError::Write(write_errno(&e)))
    }
}

impl Output for GpioOutput {
    /// One `GPIO_V2_LINE_SET_VALUES` ioctl: gpiocdev's `set_lone_value`
    /// builds the value mask on the stack and neither allocates nor locks.
    fn write(&mut self, edge: &TraceEdge) -> Result<(), OutputError> {
        self.set(edge.level)
    }

    fn park(&mut self, level: Level) -> Result<(), OutputError> {
        self.set(level)
    }
}

impl Drop for GpioOutput {
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
            "no GPIO chip `{chip}`: no GPIO chips found (no /dev/gpiochip*): this board has no GPIO driver loaded or the kernel lacks the GPIO character device (needs CONFIG_GPIO_CDEV); without GPIO hardware use --output sim"
        )
    } else {
        format!(
            "no GPIO chip `{chip}`; CHIP is a /dev/gpiochipN path, a chip name or a chip label. GPIO chips here:\n{}",
            chip_list(available)
        )
    }
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
pub fn open(chip: &str, line: &str, idle: Level) -> Result<GpioOutput, GpioError> {
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
    Ok(GpioOutput {
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
    fn set(&mut self, mask: u64, levels: u64) -> Result<(), OutputError> {
        fill_values(&mut self.values, &self.offsets, mask, levels);
        self.request
            .set_values(&self.values)
            .map_err(|e| OutputError::Write(write_errno(&e)))
    }
}

impl Bank for GpioBank {
    fn write(&mut self, _scheduled_ns: u64, mask: u64, levels: u64) -> Result<(), OutputError> {
        self.set(mask, levels)
    }

    fn park(&mut self, bit: u32, level: Level) -> Result<(), OutputError> {
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

/// Finds the chip CHIP and its line LINE (as [`open`] does), for tools that
/// request the line themselves; returns the open chip, its summary and the
/// line's info.
pub fn resolve_line(chip: &str, line: &str) -> Result<(Chip, ChipSummary, LineInfo), GpioError> {
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

/// `NAME (offset N)` or `offset N` for messages.
pub fn describe_line(info: &LineInfo) -> String {
    line_title(info)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chip(n: u32, label: &str, lines: u32) -> ChipSummary {
        ChipSummary {
            path: format!("/dev/gpiochip{n}").into(),
            name: format!("gpiochip{n}"),
            label: label.into(),
            num_lines: lines,
            unreadable: None,
        }
    }

    fn pi4() -> Vec<ChipSummary> {
        vec![
            chip(0, "pinctrl-bcm2711", 58),
            chip(1, "raspberrypi-exp-gpio", 8),
        ]
    }

    fn line(offset: Offset, name: &str) -> LineInfo {
        LineInfo {
            offset,
            name: name.into(),
            ..Default::default()
        }
    }

    fn bcm_lines() -> Vec<LineInfo> {
        (0..58).map(|o| line(o, &format!("GPIO{o}"))).collect()
    }

    #[test]
    fn gpio_chip_spec_parses_path_name_label_and_number() {
        assert_eq!(
            ChipSpec::parse("/dev/gpiochip0"),
            ChipSpec::Path("/dev/gpiochip0".into())
        );
        assert_eq!(
            ChipSpec::parse("gpiochip0"),
            ChipSpec::NameOrLabel("gpiochip0".into())
        );
        assert_eq!(
            ChipSpec::parse("pinctrl-rp1"),
            ChipSpec::NameOrLabel("pinctrl-rp1".into())
        );
        assert_eq!(
            ChipSpec::parse("4"),
            ChipSpec::NameOrLabel("gpiochip4".into())
        );
    }

    #[test]
    fn gpio_line_spec_parses_offset_and_name() {
        assert_eq!(LineSpec::parse("18"), LineSpec::Offset(18));
        assert_eq!(LineSpec::parse("GPIO18"), LineSpec::Name("GPIO18".into()));
        assert_eq!(LineSpec::parse("+18"), LineSpec::Name("+18".into()));
        assert_eq!(LineSpec::parse("-1"), LineSpec::Name("-1".into()));
    }

    #[test]
    fn gpio_find_chip_by_path_name_and_label() {
        let chips = pi4();
        assert_eq!(
            find_chip("/dev/gpiochip1", &chips).unwrap().name,
            "gpiochip1"
        );
        assert_eq!(find_chip("gpiochip1", &chips).unwrap().name, "gpiochip1");
        assert_eq!(find_chip("1", &chips).unwrap().name, "gpiochip1");
        assert_eq!(
            find_chip("pinctrl-bcm2711", &chips).unwrap().path,
            Path::new("/dev/gpiochip0")
        );
    }

    #[test]
    fn gpio_find_chip_prefers_name_over_label() {
        let chips = vec![chip(0, "gpiochip1", 4), chip(1, "x", 4)];
        assert_eq!(find_chip("gpiochip1", &chips).unwrap().name, "gpiochip1");
    }

    #[test]
    fn gpio_find_chip_unknown_lists_the_chips() {
        let e = find_chip("pinctrl-rp1", &pi4()).unwrap_err();
        assert!(matches!(e, GpioError::NoSuchChip { .. }));
        let msg = e.to_string();
        assert!(msg.contains("`pinctrl-rp1`"), "{msg}");
        assert!(
            msg.contains("/dev/gpiochip0 (gpiochip0, pinctrl-bcm2711, 58 lines)"),
            "{msg}"
        );
        assert!(
            msg.contains("/dev/gpiochip1 (gpiochip1, raspberrypi-exp-gpio, 8 lines)"),
            "{msg}"
        );
        let e = find_chip("/dev/gpiochip7", &pi4()).unwrap_err();
        assert!(matches!(e, GpioError::NoSuchChip { .. }));
    }

    #[test]
    fn gpio_find_chip_with_no_chips_says_none_found() {
        let msg = find_chip("gpiochip0", &[]).unwrap_err().to_string();
        assert!(msg.contains("no GPIO chips found"), "{msg}");
        assert!(msg.contains("CONFIG_GPIO_CDEV"), "{msg}");
    }

    #[test]
    fn gpio_find_chip_shared_label_is_ambiguous() {
        let chips = vec![chip(0, "gpio-sim", 4), chip(1, "gpio-sim", 4)];
        let e = find_chip("gpio-sim", &chips).unwrap_err();
        assert!(matches!(&e, GpioError::AmbiguousChip { matches, .. } if matches.len() == 2));
        assert!(e.to_string().contains("/dev/gpiochip1"));
    }

    #[test]
    fn gpio_find_chip_unreadable_is_permission_denied() {
        let mut chips = pi4();
        chips[0].unreadable = Some(Errno::EACCES);
        assert_eq!(
            chips[0].to_string(),
            "/dev/gpiochip0 (gpiochip0, cannot open: EACCES: Permission denied)"
        );
        let e = find_chip("gpiochip0", &chips).unwrap_err();
        assert!(matches!(e, GpioError::PermissionDenied { .. }), "{e}");
        chips[0].unreadable = Some(Errno::ENOTTY);
        let e = find_chip("gpiochip0", &chips).unwrap_err();
        assert!(matches!(e, GpioError::NoCdev { .. }), "{e}");
    }

    #[test]
    fn gpio_find_line_by_offset_and_name() {
        let c = &pi4()[0];
        let lines = bcm_lines();
        assert_eq!(find_line(c, "18", &lines).unwrap().offset, 18);
        assert_eq!(find_line(c, "GPIO18", &lines).unwrap().offset, 18);
        assert_eq!(find_line(c, "gpio18", &lines).unwrap().offset, 18);
        assert_eq!(find_line(c, "0", &lines).unwrap().name, "GPIO0");
    }

    #[test]
    fn gpio_find_line_case_insensitive_only_when_unique() {
        let c = chip(0, "", 2);
        let lines = vec![line(0, "led"), line(1, "LED")];
        assert_eq!(find_line(&c, "LED", &lines).unwrap().offset, 1);
        assert!(find_line(&c, "Led", &lines).is_err());
    }

    #[test]
    fn gpio_find_line_unknown_names_count_and_examples() {
        let c = &pi4()[0];
        let lines = bcm_lines();
        let e = find_line(c, "58", &lines).unwrap_err();
        assert!(matches!(e, GpioError::NoSuchLine { num_lines: 58, .. }));
        let msg = e.to_string();
        assert!(msg.contains("`58`"), "{msg}");
        assert!(msg.contains("gpiochip0 (pinctrl-bcm2711)"), "{msg}");
        assert!(msg.contains("58 lines (offsets 0..=57)"), "{msg}");
        assert!(msg.contains("GPIO0, GPIO1"), "{msg}");
        assert!(msg.contains("GPIO7, ..."), "{msg}");
        assert!(!msg.contains("GPIO8"), "{msg}");

        let unnamed: Vec<_> = (0..4).map(|o| line(o, "")).collect();
        let msg = find_line(&chip(2, "gpio-sim.0-node0", 4), "GPIO1", &unnamed)
            .unwrap_err()
            .to_string();
        assert!(msg.contains("no names, so give an offset"), "{msg}");
        assert!(msg.contains("4 lines (offsets 0..=3)"), "{msg}");
    }

    #[test]
    fn gpio_error_messages_name_chip_line_and_fix() {
        let busy = GpioError::Busy {
            chip: "gpiochip0".into(),
            line: "GPIO18 (offset 18)".into(),
            consumer: "pwm".into(),
        }
        .to_string();
        assert!(
            busy.starts_with("GPIO18 (offset 18) on gpiochip0 is in use by `pwm`"),
            "{busy}"
        );
        assert!(busy.contains("pick another line"), "{busy}");
        let kernel = GpioError::Busy {
            chip: "gpiochip0".into(),
            line: "GPIO18 (offset 18)".into(),
            consumer: String::new(),
        }
        .to_string();
        assert!(kernel.contains("in use by the kernel"), "{kernel}");

        let perm = GpioError::PermissionDenied {
            chip: "gpiochip0".into(),
            path: "/dev/gpiochip0".into(),
        }
        .to_string();
        assert!(perm.contains("/dev/gpiochip0"), "{perm}");
        assert!(perm.contains("sudo usermod -aG gpio $USER"), "{perm}");
        assert!(perm.contains("udev rule"), "{perm}");

        let cdev = GpioError::NoCdev {
            chip: "gpiochip0".into(),
            errno: Errno::ENOTTY,
        }
        .to_string();
        assert!(cdev.contains("gpiochip0"), "{cdev}");
        assert!(cdev.contains("CONFIG_GPIO_CDEV"), "{cdev}");
        assert!(cdev.contains("ENOTTY"), "{cdev}");

        let failed = GpioError::Failed {
            chip: "gpiochip0".into(),
            line: Some("GPIO18 (offset 18)".into()),
            op: "requesting the line as an output",
            detail: "EIO".into(),
        }
        .to_string();
        assert_eq!(
            failed,
            "GPIO chip gpiochip0, GPIO18 (offset 18): requesting the line as an output failed: EIO"
        );
    }

    #[test]
    fn gpio_open_missing_chip_is_no_such_chip() {
        let e = open("gpiochip99", "3", Level::Low).unwrap_err();
        assert!(matches!(e, GpioError::NoSuchChip { .. }), "{e}");
        assert!(e.to_string().contains("gpiochip99"), "{e}");
        let e = open("/nonexistent/gpiochip0", "3", Level::Low).unwrap_err();
        assert!(matches!(e, GpioError::NoSuchChip { .. }), "{e}");
    }

    #[test]
    fn gpio_open_non_gpio_device_is_not_a_chip() {
        let e = open("/dev/null", "0", Level::Low).unwrap_err();
        assert!(matches!(e, GpioError::NotAChip { .. }), "{e}");
        assert!(e.to_string().contains("/dev/null"), "{e}");
    }

    #[test]
    fn gpio_describe_chips_matches_the_system() {
        let chips = list_chips();
        let text = describe_chips();
        if chips.is_empty() {
            assert_eq!(text, "no GPIO chips found");
        } else {
            assert!(text.contains(&chips[0].path.display().to_string()));
        }
    }

    #[test]
    fn gpio_errno_mapping() {
        let uapi = |n: Errno| {
            gpiocdev::Error::Uapi(
                gpiocdev::UapiCall::GetLine,
                gpiocdev_uapi::Error::Os(gpiocdev_uapi::Errno(n as i32)),
            )
        };
        assert_eq!(errno_of(&uapi(Errno::EBUSY)), Some(Errno::EBUSY));
        assert_eq!(write_errno(&uapi(Errno::ENOTTY)), Errno::ENOTTY);
        let under = gpiocdev::Error::Uapi(
            gpiocdev::UapiCall::GetLineValues,
            gpiocdev_uapi::Error::UnderRead(gpiocdev_uapi::v2::UnderReadError {
                obj: "x",
                expected: 8,
                found: 0,
            }),
        );
        assert_eq!(errno_of(&under), None);
        assert_eq!(write_errno(&under), Errno::EIO);
        let no_code = gpiocdev::Error::from(std::io::Error::other("x"));
        assert_eq!(errno_of(&no_code), None);
        let os = gpiocdev::Error::from(std::io::Error::from_raw_os_error(libc_eacces()));
        assert_eq!(errno_of(&os), Some(Errno::EACCES));
        assert_eq!(write_errno(&os), Errno::EACCES);
        let other = gpiocdev::Error::InvalidArgument("x".into());
        assert_eq!(errno_of(&other), None);
        assert_eq!(write_errno(&other), Errno::EIO);
    }

    fn libc_eacces() -> i32 {
        Errno::EACCES as i32
    }

    #[test]
    fn gpio_level_high_is_active() {
        assert_eq!(value_of(Level::High), Value::Active);
        assert_eq!(value_of(Level::Low), Value::Inactive);
    }
}
