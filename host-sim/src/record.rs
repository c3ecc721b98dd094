//! Frames → record: the one rule that turns the loop's sample frames into the rows `identify`
//! reads, for `host-sim link excite|track --record` and `host-sim capture` alike.
//!
//! **Timing** (`firmware/src/xy_loop.rs`, one tick j at the loop period T):
//!
//! ```text
//! tick j:   x_j = sensor            read first, at the start of the tick
//!           u_j = guard(...)        computed, then written to the DAC and held until tick j+1's write
//!           frame j = {r_j, u_j, x_j}
//! ```
//!
//! So x_j answers u_{j−1}: the voltage written in tick j shows first in tick j+1's reading, after
//! the stage moved under it for one period. A frame holds a voltage and the reading *before* it.
//!
//! **Rule.** Row j holds the voltage applied in tick j, the reference it was computed for and the
//! reading that answers it:
//!
//! ```text
//! row j = { t_j = j·m / f_loop,  u = u_j,  r = r_j,  y = x_{j+1} }
//! ```
//!
//! (m the decimation, f_loop the loop rate, j the frame number). At m = 1 the reading is the
//! next frame's: a frame whose next frame is missing (lost in a gap, or left out for a failed
//! read) gives no row, nor does the last frame, so N contiguous frames give N − 1 rows. At
//! m > 1 the frames do not hold tick j·m + 1, whose reading answers u_j; the row then takes the
//! reading of its own frame, which answers the voltage of the tick before (m ticks after the
//! previous frame's), so the reading leads the voltage by one tick ([`Record::reading_lead_ticks`]
//! is 1 and both commands say so). Sign convention of the lead: y of the row was read one tick
//! *before* u was written.
//!
//! A plant whose response reaches the sensor within one loop period (the stage's lag) thus shows
//! no delay in the record at m = 1: identify's model maps u to y in the same row, as it does on a
//! simulated record.

use crate::csv::{CsvError, Table};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// One frame as the loop produced it, its sequence number unwrapped (frames 0, 1, … of the
/// record, or since boot), per axis x, y.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopFrame {
    /// Frame number, unwrapped (+1 per frame the loop produced).
    pub sequence: u64,
    /// Reference of the tick \[m\] (NaN during open-loop excitation).
    pub reference_m: [f32; 2],
    /// Voltage applied in the tick (after the guard) \[V\].
    pub commanded_v: [f32; 2],
    /// Sensor reading at the start of the tick \[m\].
    pub sensor_m: [f32; 2],
}

impl LoopFrame {
    /// A link frame (received, or read from the images' text form), numbered `sequence`.
    pub fn from_link(f: &piezo_link::Frame, sequence: u64) -> Self {
        Self {
            sequence,
            reference_m: f.reference_m,
            commanded_v: f.commanded_v,
            sensor_m: f.sensor_m,
        }
    }
}

/// One row of a record: the voltage of frame `sequence`'s tick, its reference and the reading
/// that answers it (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Row {
    /// Number of the frame whose voltage and reference the row holds.
    pub sequence: u64,
    /// r \[m\], x and y.
    pub reference_m: [f32; 2],
    /// u \[V\], x and y.
    pub commanded_v: [f32; 2],
    /// y \[m\], x and y: the reading that answers `commanded_v`.
    pub sensor_m: [f32; 2],
}

/// Time base: frame k at t = k·decimation / loop_rate_hz.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeBase {
    /// Loop rate \[Hz\].
    pub loop_rate_hz: f64,
    /// Ticks per frame.
    pub decimation: u32,
}

impl TimeBase {
    /// Time of frame `k` \[s\].
    pub fn time_s(&self, k: u64) -> f64 {
        (k as f64) * f64::from(self.decimation) / self.loop_rate_hz
    }
}

/// Which axes go into the CSV.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum AxisChoice {
    /// x only: `t_s, u_V, y_m[, r_m]`.
    X,
    /// y only: `t_s, u_V, y_m[, r_m]`.
    Y,
    /// Both: `t_s, ux_V, uy_V, x_m, y_m[, rx_m, ry_m]`.
    Both,
}

/// A record: the rows of the rule, on their time base.
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    /// Rows, in frame order.
    pub rows: Vec<Row>,
    /// Time base of the frames.
    pub time: TimeBase,
    /// Ticks by which each row's reading was taken before its voltage was written: 0 at
    /// decimation 1 (the reading answers the voltage), 1 at a larger decimation.
    pub reading_lead_ticks: u32,
}

/// The rule of the module doc: `frames` in order (increasing sequence numbers, gaps allowed)
/// at the decimation of `time`.
pub fn record(frames: &[LoopFrame], time: TimeBase) -> Record {
    let row = |voltage: &LoopFrame, reading: &LoopFrame| Row {
        sequence: voltage.sequence,
        reference_m: voltage.reference_m,
        commanded_v: voltage.commanded_v,
        sensor_m: reading.sensor_m,
    };
    let (rows, reading_lead_ticks) = if time.decimation <= 1 {
        let rows = frames
            .windows(2)
            .filter(|w| w[1].sequence == w[0].sequence + 1)
            .map(|w| row(&w[0], &w[1]))
            .collect();
        (rows, 0)
    } else {
        (frames.iter().map(|f| row(f, f)).collect(), 1)
    };
    Record {
        rows,
        time,
        reading_lead_ticks,
    }
}

impl Record {
    /// A sentence for a command's summary when the readings lead their voltages, else `None`.
    pub fn lead_note(&self) -> Option<String> {
        (self.reading_lead_ticks > 0).then(|| {
            format!(
                "at decimation {} the frames do not hold the reading that answers each voltage \
                 (the next tick's): each row's reading is its own frame's, {} tick ({} s) before \
                 the voltage; record at decimation 1 for identification",
                self.time.decimation,
                self.reading_lead_ticks,
                f64::from(self.reading_lead_ticks) / self.time.loop_rate_hz
            )
        })
    }

    /// Contiguous-run index per row: +1 wherever a row's frame does not follow the previous row's.
    pub fn segments(&self) -> Vec<u32> {
        let mut seg = 0u32;
        let mut prev: Option<u64> = None;
        self.rows
            .iter()
            .map(|r| {
                if prev.is_some_and(|p| r.sequence != p + 1) {
                    seg += 1;
                }
                prev = Some(r.sequence);
                seg
            })
            .collect()
    }

    /// The columns of `axis` (with the references if `reference`, with `segment_1` if
    /// `with_segments`), t from the frame numbers of the time base.
    pub fn table(&self, axis: AxisChoice, reference: bool, with_segments: bool) -> RecordTable {
        // (name, axis, field: 0 reference, 1 voltage, 2 reading)
        let picks: Vec<(&str, usize, usize)> = match axis {
            AxisChoice::X | AxisChoice::Y => {
                let a = usize::from(axis == AxisChoice::Y);
                let mut p = vec![("u_V", a, 1), ("y_m", a, 2)];
                if reference {
                    p.push(("r_m", a, 0));
                }
                p
            }
            AxisChoice::Both => {
                let mut p = vec![("ux_V", 0, 1), ("uy_V", 1, 1), ("x_m", 0, 2), ("y_m", 1, 2)];
                if reference {
                    p.extend([("rx_m", 0, 0), ("ry_m", 1, 0)]);
                }
                p
            }
        };
        let field = |r: &Row, a: usize, c: usize| match c {
            0 => r.reference_m[a],
            1 => r.commanded_v[a],
            _ => r.sensor_m[a],
        };
        let mut names = vec!["t_s".to_string()];
        names.extend(picks.iter().map(|p| p.0.to_string()));
        if with_segments {
            names.push("segment_1".into());
        }
        RecordTable {
            names,
            t_s: self
                .rows
                .iter()
                .map(|r| self.time.time_s(r.sequence))
                .collect(),
            data: picks
                .iter()
                .map(|&(_, a, c)| self.rows.iter().map(|r| field(r, a, c)).collect())
                .collect(),
            segment: with_segments.then(|| self.segments()),
        }
    }
}

/// Columns of a record's CSV (f32 values kept as the firmware sent them; `t_s` and `segment_1`
/// as f64).
#[derive(Debug, Clone, PartialEq)]
pub struct RecordTable {
    /// Column names with units.
    pub names: Vec<String>,
    /// Time \[s\].
    pub t_s: Vec<f64>,
    /// Data columns, in the order of `names` after `t_s` (and before `segment_1`).
    pub data: Vec<Vec<f32>>,
    /// Contiguous-run index per row, when asked for.
    pub segment: Option<Vec<u32>>,
}

impl RecordTable {
    /// As a [`Table`] of f64 (for tests and in-memory use).
    pub fn to_table(&self) -> Table {
        let mut columns = vec![self.t_s.clone()];
        columns.extend(
            self.data
                .iter()
                .map(|c| c.iter().map(|&v| f64::from(v)).collect()),
        );
        if let Some(s) = &self.segment {
            columns.push(s.iter().map(|&v| f64::from(v)).collect());
        }
        Table {
            path: PathBuf::new(),
            names: self.names.clone(),
            columns,
        }
    }

    /// Writes the CSV with `#` comment lines first (which [`crate::csv::read_csv`] skips); values
    /// in f32's shortest round-trip form.
    pub fn write(&self, path: &Path, comments: &[String]) -> Result<(), CsvError> {
        let io = |e: std::io::Error| CsvError::Io {
            path: path.into(),
            message: e.to_string(),
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            fs::create_dir_all(dir).map_err(io)?;
        }
        let mut out = std::io::BufWriter::new(fs::File::create(path).map_err(io)?);
        for c in comments {
            writeln!(out, "# {c}").map_err(io)?;
        }
        writeln!(out, "{}", self.names.join(",")).map_err(io)?;
        for (r, t) in self.t_s.iter().enumerate() {
            write!(out, "{t}").map_err(io)?;
            for c in &self.data {
                write!(out, ",{}", c[r]).map_err(io)?;
            }
            if let Some(s) = &self.segment {
                write!(out, ",{}", s[r]).map_err(io)?;
            }
            writeln!(out).map_err(io)?;
        }
        out.flush().map_err(io)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(k: u64) -> LoopFrame {
        let v = k as f32;
        LoopFrame {
            sequence: k,
            reference_m: [v * 1e-6, -v * 1e-6],
            commanded_v: [v, 2.0 * v],
            sensor_m: [v * 1e-7, v * 2e-7],
        }
    }

    #[test]
    fn decimation_1_pairs_each_voltage_with_the_next_reading() {
        let frames: Vec<LoopFrame> = [3, 4, 5, 7, 8].map(frame).to_vec();
        let time = TimeBase {
            loop_rate_hz: 1e4,
            decimation: 1,
        };
        let r = record(&frames, time);
        assert_eq!(r.reading_lead_ticks, 0);
        // 3→4, 4→5, 7→8: frame 5 has no next frame (6 lost), frame 8 is the last.
        assert_eq!(
            r.rows.iter().map(|r| r.sequence).collect::<Vec<_>>(),
            [3, 4, 7]
        );
        for row in &r.rows {
            let (now, next) = (frame(row.sequence), frame(row.sequence + 1));
            assert_eq!(row.commanded_v, now.commanded_v);
            assert_eq!(row.reference_m, now.reference_m);
            assert_eq!(row.sensor_m, next.sensor_m);
        }
        assert_eq!(r.segments(), [0, 0, 1]);
        let t = r.table(AxisChoice::Both, true, true);
        assert_eq!(
            t.names,
            [
                "t_s",
                "ux_V",
                "uy_V",
                "x_m",
                "y_m",
                "rx_m",
                "ry_m",
                "segment_1"
            ]
        );
        assert_eq!(t.t_s, [3e-4, 4e-4, 7e-4]);
        assert!(r.lead_note().is_none());
    }

    #[test]
    fn a_larger_decimation_pairs_within_the_frame_and_says_so() {
        let frames: Vec<LoopFrame> = (0..4).map(frame).collect();
        let r = record(
            &frames,
            TimeBase {
                loop_rate_hz: 1e4,
                decimation: 10,
            },
        );
        assert_eq!(r.rows.len(), 4);
        assert_eq!(r.rows[2].sensor_m, frame(2).sensor_m);
        assert_eq!(r.reading_lead_ticks, 1);
        assert!(r.lead_note().unwrap().contains("1 tick (0.0001 s)"));
        let t = r.table(AxisChoice::Y, false, false);
        assert_eq!(t.names, ["t_s", "u_V", "y_m"]);
        assert_eq!(t.data[0], [0.0, 2.0, 4.0, 6.0]);
        assert_eq!(t.t_s[3], 3e-3);
    }
}
