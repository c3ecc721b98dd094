//! `host-sim capture`: a decoded firmware log (QEMU semihosting output, or defmt printed by
//! `probe-rs run` / `defmt-print`) turned into the CSV that `host-sim identify` reads.
//!
//! **Input.** Lines are read one by one; everything that is neither a boot line nor a frame is
//! ignored (counters, PASS, probe-rs location lines `└─ …`). A frame is any line that contains
//! `frame <n>: ` (a timestamp or level before it is allowed), in the firmware's text form
//! ([`piezo_link::text`], which the firmware prints with and this module reads with):
//!
//! ```text
//! frame 12: x ref 0.000019 m cmd 10 V sensor 0 m | y ref 0.000004 m cmd 10 V sensor 0 m
//! ```
//!
//! Anything after the y sensor field must start with `|` (ignored).
//! The boot line `parameters <version> (<file>), fnv1a32 0x<hash>, fingerprint 0x<hash>, loop
//! <rate> Hz, one frame every <n> ticks` gives the set (the CSV's first comment repeats its
//! version and hashes; the fingerprint may be absent) and the time base: frame k was produced at
//! t = k·n / rate after boot.
//! `--rate` and `--decimation` replace (or supply) those two numbers.
//!
//! **Output.** Column names carry units ([`crate::csv`]): with `--axis both` (default)
//! `t_s, ux_V, uy_V, x_m, y_m, rx_m, ry_m` (the same names as `host-sim simulate --plant
//! xy-stage`, plus the references); with `--axis x` or `--axis y` `t_s, u_V, y_m, r_m` for that
//! axis (`u` commanded volts after the safety guard, `y` sensor metres, `r` the reference).
//! The rows follow [`crate::record`], as `host-sim link`'s records do: each row holds a tick's
//! voltage and reference with the reading that answers it, the next frame's (a frame's own
//! reading was taken before its voltage was written), at t of the voltage's tick; N contiguous
//! frames give N − 1 rows. At a decimation above 1 the answering reading is not in the log and
//! the row takes its own frame's, one tick early (said on stderr and in the file).
//! Values are written as the firmware printed them (f32, shortest round trip). Comment lines
//! (`#`, skipped by the CSV reader) name the log, the parameter set and the time base.
//!
//! **Gaps.** Sequence numbers must step by one (wrapping at 2³²). A gap (frames lost in the link
//! or in the firmware's queue) stops the capture with an error naming the line, unless
//! `--allow-gaps` is given. Then every row whose frames are there is written, `t_s` keeps the true time of each frame
//! (so a gap is a jump in `t_s`), and an extra column `segment_1` numbers the contiguous runs
//! (0, 1, …) so a reader can split them. A frame with a non-finite value (NaN sensor: the read
//! failed) is an error too, and with `--allow-gaps` it is left out and counted as a gap. Gaps are
//! always reported on stderr and in the summary line (count, frames lost, the first five). A
//! sequence number that goes backwards means a second run in the same log: always an error.

use crate::csv::CsvError;
use crate::record::{record, LoopFrame, Record};
use std::fmt;
use std::fs;
use std::path::{Path, PathBuf};

/// `host-sim capture --help` text after the options.
pub const HELP: &str = "Input: lines `frame <n>: x ref <m> m cmd <V> V sensor <m> m | y ref <m> m cmd <V> V sensor <m> m` \
(anything before `frame`, e.g. a defmt timestamp and level, is allowed; other lines are ignored) and the boot line \
`parameters <version> (<file>), fnv1a32 0x<hash>, fingerprint 0x<hash>, loop <rate> Hz, one frame every <n> ticks` (the fingerprint may be absent), which gives t_s = n * sequence / rate.\n\
Output: --axis both: t_s,ux_V,uy_V,x_m,y_m,rx_m,ry_m; --axis x|y: t_s,u_V,y_m,r_m (u commanded volts, y sensor metres, r reference); \
each row holds a frame's voltage and reference with the next frame's reading, the one that answers it (at a decimation above 1 its own frame's, one tick early).\n\
Gaps: a missing sequence number, or a frame with a NaN value, stops with an error naming the line. With --allow-gaps every row whose frames are there \
is written with its true t_s and a segment_1 column numbering the contiguous runs; the gaps are listed on stderr and in the summary.\n\
Board: cd firmware && cargo run --release --features board --bin board > board.log, then host-sim capture --log board.log --out board.csv.\n\
QEMU: cd firmware && cargo build --release --features qemu,frames-all --bin qemu, run it with ./run-qemu.sh > qemu.log.";

/// Gaps listed by name in the summary.
pub const GAPS_LISTED: usize = 5;

/// One frame as printed: the firmware's text form.
pub use piezo_link::Frame;

/// The boot line's fields.
#[derive(Debug, Clone, PartialEq)]
pub struct BootLine {
    /// 1-based line number in the log.
    pub line: usize,
    /// Parameter-file version string (`name version`).
    pub version: String,
    /// FNV-1a of the parameter file, as printed (`0x…`).
    pub fnv1a32: String,
    /// The running set's content fingerprint (`piezo_link::ModelSet::fingerprint`), as printed
    /// (`0x…`), if the line states it.
    pub fingerprint: Option<String>,
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Ticks per frame, if the line states it.
    pub decimation: Option<u32>,
}

/// A missing stretch of sequence numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Gap {
    /// Line of the first frame after the gap (1-based).
    pub line: usize,
    /// Sequence number expected there.
    pub expected: u64,
    /// Frames missing (including frames dropped for non-finite values).
    pub missing: u64,
}

/// A parsed log: frames in order, with unwrapped sequence numbers and their lines.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CapturedLog {
    /// The log file (for messages).
    pub path: PathBuf,
    /// Boot line, if present.
    pub boot: Option<BootLine>,
    /// (line, unwrapped sequence, frame).
    pub frames: Vec<(usize, u64, Frame)>,
    /// Gaps found (only non-empty with `allow_gaps`).
    pub gaps: Vec<Gap>,
    /// Lines read.
    pub lines: usize,
}

impl CapturedLog {
    /// Frames lost in all gaps.
    pub fn lost(&self) -> u64 {
        self.gaps.iter().map(|g| g.missing).sum()
    }

    /// `N gaps (M frames lost)` and the first [`GAPS_LISTED`] gaps.
    pub fn gap_summary(&self) -> String {
        if self.gaps.is_empty() {
            return "0 gaps".into();
        }
        let first: Vec<String> = self
            .gaps
            .iter()
            .take(GAPS_LISTED)
            .map(|g| {
                format!(
                    "{}:{}: {} missing from frame {}",
                    self.path.display(),
                    g.line,
                    g.missing,
                    g.expected
                )
            })
            .collect();
        format!(
            "{} gaps ({} frames lost); first: {}",
            self.gaps.len(),
            self.lost(),
            first.join("; ")
        )
    }
}

/// Capture errors; each names the log file and, where there is one, the line.
#[derive(Debug, Clone, PartialEq)]
pub enum CaptureError {
    /// The log could not be read.
    Io {
        /// File.
        path: PathBuf,
        /// OS message.
        message: String,
    },
    /// A line that starts a frame (or a boot line) but does not parse.
    Malformed {
        /// File.
        path: PathBuf,
        /// Line (1-based).
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// Sequence gap (without `--allow-gaps`).
    Gap {
        /// File.
        path: PathBuf,
        /// Line of the frame after the gap.
        line: usize,
        /// Sequence number expected.
        expected: u64,
        /// Sequence number found.
        found: u64,
    },
    /// A non-finite value in a frame (without `--allow-gaps`).
    NonFinite {
        /// File.
        path: PathBuf,
        /// Line.
        line: usize,
        /// Field, e.g. `x sensor`.
        field: &'static str,
    },
    /// The sequence number goes backwards: a second run in the same log.
    Restart {
        /// File.
        path: PathBuf,
        /// Line.
        line: usize,
        /// Sequence number before.
        previous: u32,
        /// Sequence number found.
        found: u32,
    },
    /// No frame in the log.
    NoFrames {
        /// File.
        path: PathBuf,
        /// Lines read.
        lines: usize,
    },
    /// Frames, but no row: at decimation 1 no frame is followed by the next one (whose reading
    /// answers its voltage).
    NoRows {
        /// File.
        path: PathBuf,
        /// Frames read.
        frames: usize,
    },
    /// No loop rate: no boot line and no `--rate`.
    NoRate {
        /// File.
        path: PathBuf,
    },
    /// Writing the CSV failed.
    Write(CsvError),
}

impl fmt::Display for CaptureError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::Malformed { path, line, message } => {
                write!(f, "{}:{line}: malformed frame line: {message}", path.display())
            }
            Self::Gap { path, line, expected, found } => write!(
                f,
                "{}:{line}: sequence gap: expected frame {expected}, found {found} ({} frames lost); \
                 --allow-gaps writes the rows around it with a segment_1 column",
                path.display(),
                found - expected
            ),
            Self::NonFinite { path, line, field } => write!(
                f,
                "{}:{line}: {field} is not finite (failed sensor read?); --allow-gaps leaves such frames out",
                path.display()
            ),
            Self::Restart { path, line, previous, found } => write!(
                f,
                "{}:{line}: sequence goes back from {previous} to {found}: a second run in the same log; \
                 capture one run per file",
                path.display()
            ),
            Self::NoFrames { path, lines } => write!(
                f,
                "{}: no frame lines (`frame <n>: x ref …`) in {lines} lines",
                path.display()
            ),
            Self::NoRows { path, frames } => write!(
                f,
                "{}: {frames} frames but no two consecutive ones: a row pairs a frame's voltage \
                 with the next frame's reading, the one that answers it",
                path.display()
            ),
            Self::NoRate { path } => write!(
                f,
                "{}: no boot line with `loop <rate> Hz`: give --rate",
                path.display()
            ),
            Self::Write(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for CaptureError {}

fn number<T: std::str::FromStr>(word: Option<&str>, what: &str) -> crate::Result<T> {
    let w = word.ok_or_else(|| crate::Error::Data(format!("{what}: missing")))?;
    w.parse()
        .map_err(|_| crate::Error::Data(format!("{what}: `{w}` is not a number")))
}

/// Parses one log line: `None` if it is not a frame line, else the frame or what is wrong.
pub fn parse_frame_line(line: &str) -> Option<crate::Result<Frame>> {
    let text = &line[piezo_link::text::find_frame(line)?..];
    Some(
        text.parse::<Frame>()
            .map_err(|e| crate::Error::Data(e.in_text(text).to_string())),
    )
}

/// Parses a boot line (`parameters <version> (<file>), fnv1a32 0x…[, fingerprint 0x…], loop
/// <rate> Hz[, one frame every <n> ticks]`): `None` if the line is not one.
pub fn parse_boot_line(line: &str, number_1: usize) -> Option<crate::Result<BootLine>> {
    let p = line.find("parameters ")?;
    let rest = &line[p + "parameters ".len()..];
    let fnv_at = rest.find(", fnv1a32 ")?;
    Some((|| {
        let head = &rest[..fnv_at];
        let version = head.split(" (").next().unwrap_or(head).trim().to_string();
        let mut fields = rest[fnv_at + 2..].split(", ");
        let fnv1a32 = fields
            .next()
            .and_then(|f| f.strip_prefix("fnv1a32 "))
            .ok_or_else(|| crate::Error::Data("no `fnv1a32 0x…`".into()))?
            .trim()
            .to_string();
        let mut loop_field = fields
            .next()
            .ok_or_else(|| crate::Error::Data("no `loop <rate> Hz` field".into()))?
            .trim();
        let fingerprint = match loop_field.strip_prefix("fingerprint ") {
            Some(f) => {
                let f = f.trim().to_string();
                loop_field = fields
                    .next()
                    .ok_or_else(|| crate::Error::Data("no `loop <rate> Hz` field".into()))?
                    .trim();
                Some(f)
            }
            None => None,
        };
        let rate = loop_field
            .strip_prefix("loop ")
            .and_then(|s| s.strip_suffix(" Hz"))
            .ok_or_else(|| {
                crate::Error::Data(format!("expected `loop <rate> Hz`, found `{loop_field}`"))
            })?;
        let loop_rate_hz: f64 = number(Some(rate), "loop rate")?;
        if !(loop_rate_hz > 0.0 && loop_rate_hz.is_finite()) {
            return Err(crate::Error::Data(format!(
                "loop rate {loop_rate_hz} Hz is not positive"
            )));
        }
        let decimation = match fields.next() {
            Some(d) => {
                let n = d
                    .trim()
                    .strip_prefix("one frame every ")
                    .and_then(|s| s.split_whitespace().next())
                    .ok_or_else(|| {
                        crate::Error::Data(format!(
                            "expected `one frame every <n> ticks`, found `{d}`"
                        ))
                    })?;
                let n: u32 = number(Some(n), "frame decimation")?;
                Some(n.max(1))
            }
            None => None,
        };
        Ok(BootLine {
            line: number_1,
            version,
            fnv1a32,
            fingerprint,
            loop_rate_hz,
            decimation,
        })
    })())
}

/// Reads a log file; see [`parse_log`].
pub fn read_log(path: &Path, allow_gaps: bool) -> Result<CapturedLog, CaptureError> {
    let bytes = fs::read(path).map_err(|e| CaptureError::Io {
        path: path.into(),
        message: e.to_string(),
    })?;
    // probe-rs may colour its output; invalid UTF-8 is replaced, not fatal.
    parse_log(path, &String::from_utf8_lossy(&bytes), allow_gaps)
}

/// Parses log text (`path` only names it in messages). Without `allow_gaps` the first gap or
/// non-finite value is an error; with it they are recorded in [`CapturedLog::gaps`].
pub fn parse_log(path: &Path, text: &str, allow_gaps: bool) -> Result<CapturedLog, CaptureError> {
    let mut log = CapturedLog {
        path: path.into(),
        ..CapturedLog::default()
    };
    // (printed, unwrapped) sequence number of the last frame seen (kept or dropped).
    let mut last: Option<(u32, u64)> = None;
    let mut pending_gap: Option<Gap> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        log.lines = line;
        let malformed = |message: String| CaptureError::Malformed {
            path: path.into(),
            line,
            message,
        };
        let frame = match parse_frame_line(raw) {
            None => {
                if let Some(boot) = parse_boot_line(raw, line) {
                    let boot = boot.map_err(|m| malformed(format!("boot line: {m}")))?;
                    if let (Some(first), Some(_)) = (&log.boot, last) {
                        return Err(malformed(format!(
                            "a second boot line (the first is line {}): capture one run per file",
                            first.line
                        )));
                    }
                    log.boot = Some(boot);
                }
                continue;
            }
            Some(f) => f.map_err(|e| malformed(e.to_string()))?,
        };
        let unwrapped = match last {
            None => u64::from(frame.sequence),
            Some((printed, u)) => {
                let ahead = frame.sequence.wrapping_sub(printed);
                if ahead == 0 || ahead >= u32::MAX / 2 {
                    return Err(CaptureError::Restart {
                        path: path.into(),
                        line,
                        previous: printed,
                        found: frame.sequence,
                    });
                }
                let here = u + u64::from(ahead);
                if ahead > 1 {
                    if !allow_gaps {
                        return Err(CaptureError::Gap {
                            path: path.into(),
                            line,
                            expected: u + 1,
                            found: here,
                        });
                    }
                    let g = pending_gap.get_or_insert(Gap {
                        line,
                        expected: u + 1,
                        missing: 0,
                    });
                    g.missing += u64::from(ahead - 1);
                }
                here
            }
        };
        last = Some((frame.sequence, unwrapped));
        let names = piezo_link::text::FIELDS;
        let bad = (0..2)
            .flat_map(|a| (0..3).map(move |c| (a, c)))
            .find(|&(a, c)| {
                let fields = [frame.reference_m, frame.commanded_v, frame.sensor_m];
                !fields[c][a].is_finite()
            });
        if let Some((a, c)) = bad {
            if !allow_gaps {
                return Err(CaptureError::NonFinite {
                    path: path.into(),
                    line,
                    field: names[a][c],
                });
            }
            let g = pending_gap.get_or_insert(Gap {
                line,
                expected: unwrapped,
                missing: 0,
            });
            g.missing += 1;
            continue;
        }
        if let Some(g) = pending_gap.take() {
            log.gaps.push(g);
        }
        log.frames.push((line, unwrapped, frame));
    }
    if let Some(g) = pending_gap.take() {
        log.gaps.push(g);
    }
    if log.frames.is_empty() {
        return Err(CaptureError::NoFrames {
            path: path.into(),
            lines: log.lines,
        });
    }
    Ok(log)
}

pub use crate::record::{AxisChoice, TimeBase};

impl CapturedLog {
    /// The log's frames as a record ([`crate::record`]'s rule: each voltage with the reading
    /// that answers it).
    pub fn record(&self, time: TimeBase) -> Record {
        let frames: Vec<LoopFrame> = self
            .frames
            .iter()
            .map(|(_, k, f)| LoopFrame::from_link(f, *k))
            .collect();
        record(&frames, time)
    }
}

/// Arguments of `host-sim capture`.
#[derive(Debug, Clone, clap::Args)]
pub struct CaptureArgs {
    /// Decoded firmware log: QEMU output, or defmt as printed by `probe-rs run` / `defmt-print`.
    #[arg(long)]
    pub log: PathBuf,
    /// Output CSV file (directory created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Axis to write: x or y (`t_s,u_V,y_m,r_m`) or both (`t_s,ux_V,uy_V,x_m,y_m,rx_m,ry_m`).
    #[arg(long, value_enum, default_value_t = AxisChoice::Both)]
    pub axis: AxisChoice,
    /// Loop rate (Hz), replacing the boot line's (needed when the log has no boot line).
    #[arg(long)]
    pub rate: Option<f64>,
    /// Loop ticks per frame, replacing the boot line's (default 1 when the log does not say).
    #[arg(long)]
    pub decimation: Option<u32>,
    /// Continue past sequence gaps and non-finite frames: write every good frame with its true
    /// t_s and a segment_1 column numbering the contiguous runs.
    #[arg(long = "allow-gaps")]
    pub allow_gaps: bool,
}

/// Runs `capture`: progress and gap reports go to `progress` (stderr), the summary is returned.
pub fn run(a: &CaptureArgs, progress: &mut dyn FnMut(&str)) -> crate::Result<String> {
    if let Some(r) = a.rate {
        if !(r > 0.0 && r.is_finite()) {
            return Err(crate::Error::Data(format!(
                "--rate: {r} is not a positive rate in Hz"
            )));
        }
    }
    if a.decimation == Some(0) {
        return Err(crate::Error::Data(
            "--decimation: must be at least 1".into(),
        ));
    }
    let log = read_log(&a.log, a.allow_gaps).map_err(crate::Error::from)?;
    let mut notes = Vec::new();
    let loop_rate_hz = match (a.rate, &log.boot) {
        (Some(r), Some(b)) if r != b.loop_rate_hz => {
            notes.push(format!(
                "--rate {r} Hz replaces the boot line's {} Hz",
                b.loop_rate_hz
            ));
            r
        }
        (Some(r), _) => r,
        (None, Some(b)) => b.loop_rate_hz,
        (None, None) => return Err(CaptureError::NoRate { path: log.path }.into()),
    };
    let decimation = match (a.decimation, log.boot.as_ref().and_then(|b| b.decimation)) {
        (Some(d), _) => d,
        (None, Some(d)) => d,
        (None, None) => {
            notes.push(
                "the log does not state the frame decimation: 1 assumed (--decimation)".into(),
            );
            1
        }
    };
    let time = TimeBase {
        loop_rate_hz,
        decimation,
    };
    for n in &notes {
        progress(&format!("capture: {n}"));
    }
    for g in &log.gaps {
        progress(&format!(
            "capture: {}:{}: gap, {} frames missing from frame {}",
            log.path.display(),
            g.line,
            g.missing,
            g.expected
        ));
    }
    let record = log.record(time);
    if record.rows.is_empty() {
        return Err(CaptureError::NoRows {
            path: log.path.clone(),
            frames: log.frames.len(),
        }
        .into());
    }
    if let Some(note) = record.lead_note() {
        progress(&format!("capture: {note}"));
    }
    let table = record.table(a.axis, true, a.allow_gaps);
    let (first, last) = (log.frames[0].1, log.frames[log.frames.len() - 1].1);
    let params = log.boot.as_ref().map_or_else(
        || "parameters: no boot line".to_string(),
        |b| match &b.fingerprint {
            Some(f) => format!(
                "parameters {}, fnv1a32 {}, fingerprint {f}",
                b.version, b.fnv1a32
            ),
            None => format!("parameters {}, fnv1a32 {}", b.version, b.fnv1a32),
        },
    );
    let comments = vec![
        format!("host-sim capture of {} ({params})", a.log.display()),
        format!(
            "time base: loop {loop_rate_hz} Hz, one frame every {decimation} ticks: t_s = sequence * {} s",
            f64::from(decimation) / loop_rate_hz
        ),
        format!(
            "frames {first}..={last}, {} read, {}; {} rows: {}",
            log.frames.len(),
            log.gap_summary(),
            record.rows.len(),
            record.lead_note().unwrap_or_else(|| {
                "each voltage with the next frame's reading, the one that answers it".into()
            })
        ),
    ];
    table
        .write(&a.out, &comments)
        .map_err(|e| crate::Error::Data(format!("--out: {e}")))?;
    let summary = format!(
        "capture: {} frames {first}..={last} from {} ({params}; {} lines) at {} Hz per frame, {}; {} rows written to {} ({})",
        log.frames.len(),
        a.log.display(),
        log.lines,
        loop_rate_hz / f64::from(decimation),
        log.gap_summary(),
        record.rows.len(),
        a.out.display(),
        table.names.join(",")
    );
    if !log.gaps.is_empty() {
        progress(&summary);
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_boot_line_gives_its_fingerprint_when_it_has_one() {
        let with = "piezo-firmware qemu: parameters xy-stage 3 (params/xy-stage.toml), fnv1a32 0x0badf00d, fingerprint 0x813b1b0d, loop 20000 Hz, one frame every 10 ticks";
        let b = parse_boot_line(with, 4).unwrap().unwrap();
        assert_eq!(b.fingerprint.as_deref(), Some("0x813b1b0d"));
        assert_eq!(b.fnv1a32, "0x0badf00d");
        assert_eq!(
            (b.loop_rate_hz, b.decimation, b.line),
            (20_000.0, Some(10), 4)
        );
        assert_eq!(b.version, "xy-stage 3");
        let without = "parameters xy-stage 3 (f.toml), fnv1a32 0x0badf00d, loop 10000 Hz";
        let b = parse_boot_line(without, 1).unwrap().unwrap();
        assert_eq!(
            (b.fingerprint, b.loop_rate_hz, b.decimation),
            (None, 10_000.0, None)
        );
        let cut = "parameters v (f), fnv1a32 0x1, fingerprint 0x2";
        assert!(parse_boot_line(cut, 1).unwrap().is_err());
    }
}
