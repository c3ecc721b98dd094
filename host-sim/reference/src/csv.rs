//! CSV files of sampled signals; every column name carries its unit as a suffix (`t_s`, `u_V`, `y_m`,
//! `ux_V`, `uy_V`, `x_m`, ...). A two-axis file holds both axes as separate columns.
//! Reader errors name the file, the line (1-based) and the column (1-based and by name). A leading
//! UTF-8 byte-order mark is skipped; every cell must be a finite number.
//!
//! A record's time column (`Rows::time`) is its sampling time base t\[k\], k = 0…N−1, checked
//! where it is read: at least two samples, strictly increasing (t\[k\] > t\[k−1\]), a median step
//! Δ̃ = median(t\[k\] − t\[k−1\]) of at least [`MIN_SAMPLE_PERIOD_S`], and every step within a
//! factor [`MAX_STEP_RATIO`] of it, Δ̃/1.5 ≤ t\[k\] − t\[k−1\] ≤ 1.5·Δ̃: the sampling is uniform up
//! to jitter, with no gap, jump or doubled sample. The tools that read records (identify,
//! close-loop, predict, compensate's reference, the `csv:` signal) all take their times from it.

use std::fmt;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Largest ratio between a record's step and its median step (and between the median step and a
/// step): a step outside Δ̃/1.5…1.5·Δ̃ is a gap, a jump or a doubled sample.
pub const MAX_STEP_RATIO: f64 = 1.5;

/// Smallest median sample period a record may have \[s\] (1 GHz): below it the times do not
/// describe a sampled actuator (and in the core's f32 they round towards zero).
pub const MIN_SAMPLE_PERIOD_S: f64 = 1e-9;

/// What a column measures, from its unit suffix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// s, ms, us/µs, ns.
    Time,
    /// V, mV, kV.
    Voltage,
    /// N, mN, kN.
    Force,
    /// m, mm, um/µm, nm, pm.
    Length,
    /// Hz.
    Frequency,
    /// V_per_s.
    VoltageRate,
    /// m_per_s.
    Speed,
    /// 1 (no dimension).
    Ratio,
}

impl Quantity {
    /// "a time", "a voltage", ….
    pub fn name(self) -> &'static str {
        match self {
            Self::Time => "a time",
            Self::Voltage => "a voltage",
            Self::Force => "a force",
            Self::Length => "a length",
            Self::Frequency => "a frequency",
            Self::VoltageRate => "a voltage rate",
            Self::Speed => "a speed",
            Self::Ratio => "a ratio",
        }
    }
}

/// Units accepted as column suffixes (after the `_` that ends the name): suffix, SI factor,
/// quantity.
pub const UNITS: [(&str, f64, Quantity); 21] = [
    ("s", 1.0, Quantity::Time),
    ("ms", 1e-3, Quantity::Time),
    ("us", 1e-6, Quantity::Time),
    ("µs", 1e-6, Quantity::Time),
    ("ns", 1e-9, Quantity::Time),
    ("V", 1.0, Quantity::Voltage),
    ("mV", 1e-3, Quantity::Voltage),
    ("kV", 1e3, Quantity::Voltage),
    ("N", 1.0, Quantity::Force),
    ("mN", 1e-3, Quantity::Force),
    ("kN", 1e3, Quantity::Force),
    ("m", 1.0, Quantity::Length),
    ("mm", 1e-3, Quantity::Length),
    ("um", 1e-6, Quantity::Length),
    ("µm", 1e-6, Quantity::Length),
    ("nm", 1e-9, Quantity::Length),
    ("pm", 1e-12, Quantity::Length),
    ("Hz", 1.0, Quantity::Frequency),
    ("V_per_s", 1.0, Quantity::VoltageRate),
    ("m_per_s", 1.0, Quantity::Speed),
    ("1", 1.0, Quantity::Ratio),
];

/// The unit of column `name`: the [`UNITS`] suffix it ends in after a `_` (the longest, so
/// `u_V_per_s` is a voltage rate), its SI factor and quantity; `None` without one.
pub fn unit_of(name: &str) -> Option<(f64, Quantity)> {
    UNITS
        .iter()
        .filter(|(u, _, _)| {
            name.len() > u.len() + 1
                && name.ends_with(u)
                && name[..name.len() - u.len()].ends_with('_')
        })
        .max_by_key(|(u, _, _)| u.len())
        .map(|&(_, f, q)| (f, q))
}

/// The suffixes of `wanted` (all when empty), comma-separated, for messages.
pub fn unit_names(wanted: &[Quantity]) -> String {
    UNITS
        .iter()
        .filter(|(_, _, q)| wanted.is_empty() || wanted.contains(q))
        .map(|(u, _, _)| *u)
        .collect::<Vec<_>>()
        .join(", ")
}

/// CSV errors.
#[derive(Debug, Clone, PartialEq)]
pub enum CsvError {
    /// Reading or writing failed.
    Io {
        /// File.
        path: PathBuf,
        /// OS message.
        message: String,
    },
    /// File has no header line.
    Empty {
        /// File.
        path: PathBuf,
    },
    /// Header column without a known unit suffix.
    NoUnit {
        /// File.
        path: PathBuf,
        /// Column (1-based).
        column: usize,
        /// Header text.
        name: String,
    },
    /// A cell that is not a finite number.
    BadNumber {
        /// File.
        path: PathBuf,
        /// Line (1-based).
        line: usize,
        /// Column (1-based).
        column: usize,
        /// Column name.
        name: String,
        /// Text found.
        given: String,
    },
    /// Wrong number of cells on a line.
    WrongCellCount {
        /// File.
        path: PathBuf,
        /// Line (1-based).
        line: usize,
        /// Cells expected.
        expected: usize,
        /// Cells found.
        found: usize,
    },
    /// A value that is finite in the file but not in the f32 the core computes in.
    BeyondF32 {
        /// File.
        path: PathBuf,
        /// Line (1-based).
        line: usize,
        /// Column (1-based).
        column: usize,
        /// Column name.
        name: String,
        /// The value, in the file's unit.
        given: f64,
    },
    /// A time column that is not a uniform sampling time base (see the module doc).
    Time {
        /// File.
        path: PathBuf,
        /// Line (1-based) of the sample at fault.
        line: usize,
        /// Column (1-based).
        column: usize,
        /// Column name.
        name: String,
        /// What is wrong.
        fault: TimeFault,
    },
    /// A requested column is missing.
    MissingColumn {
        /// File.
        path: PathBuf,
        /// Column asked for.
        name: String,
        /// Columns present.
        available: String,
    },
}

/// What is wrong with a time column.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TimeFault {
    /// Fewer than two samples: no sample period.
    TooShort {
        /// Samples found.
        samples: usize,
    },
    /// t\[k\] ≤ t\[k−1\]: the times repeat or run backwards.
    NotIncreasing {
        /// t\[k−1\] \[s\].
        previous_s: f64,
        /// Its line.
        previous_line: usize,
        /// t\[k\] \[s\].
        given_s: f64,
    },
    /// The median step is below [`MIN_SAMPLE_PERIOD_S`].
    TooFine {
        /// The median step \[s\].
        median_s: f64,
    },
    /// A step outside Δ̃/1.5…1.5·Δ̃.
    Uneven {
        /// The step t\[k\] − t\[k−1\] \[s\].
        step_s: f64,
        /// Line of t\[k−1\].
        previous_line: usize,
        /// The median step Δ̃ \[s\].
        median_s: f64,
    },
}

impl fmt::Display for TimeFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::TooShort { samples } => write!(
                f,
                "{samples} sample(s): a record needs at least two to have a sample period"
            ),
            Self::NotIncreasing {
                previous_s,
                previous_line,
                given_s,
            } => write!(
                f,
                "t = {given_s} s is not after t = {previous_s} s on line {previous_line}: the time \
                 column must increase strictly (rows repeated, reversed or out of order)"
            ),
            Self::TooFine { median_s } => write!(
                f,
                "the median step is {median_s:.3e} s, below {MIN_SAMPLE_PERIOD_S:e} s: not the \
                 times of a sampled record in seconds"
            ),
            Self::Uneven {
                step_s,
                previous_line,
                median_s,
            } => write!(
                f,
                "the step from line {previous_line} is {step_s:.4e} s, {:.3} times the median step \
                 {median_s:.4e} s (a gap, a jump or a doubled sample): a record is sampled at one \
                 period, every step within {MAX_STEP_RATIO} times the median either way",
                step_s / median_s
            ),
        }
    }
}

impl fmt::Display for CsvError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::Empty { path } => {
                write!(f, "{}: empty file, expected a header line", path.display())
            }
            Self::NoUnit { path, column, name } => write!(
                f,
                "{}:1: column {column} `{name}` {} (expected name_UNIT with UNIT one of {})",
                path.display(),
                match name.rsplit_once('_') {
                    Some((_, unit)) => format!("has an unknown unit suffix `{unit}`"),
                    None => "has no unit suffix".to_string(),
                },
                unit_names(&[])
            ),
            Self::BadNumber {
                path,
                line,
                column,
                name,
                given,
            } => write!(
                f,
                "{}:{line}: column {column} (`{name}`): `{given}` is not a finite number",
                path.display()
            ),
            Self::WrongCellCount {
                path,
                line,
                expected,
                found,
            } => {
                write!(
                    f,
                    "{}:{line}: expected {expected} cells, found {found}",
                    path.display()
                )
            }
            Self::BeyondF32 {
                path,
                line,
                column,
                name,
                given,
            } => write!(
                f,
                "{}:{line}: column {column} (`{name}`): {given:e} is beyond the range of the f32 \
                 the core computes in (|v| <= {:e} in SI units)",
                path.display(),
                f32::MAX
            ),
            Self::Time {
                path,
                line,
                column,
                name,
                fault,
            } => write!(
                f,
                "{}:{line}: column {column} (`{name}`): {fault}",
                path.display()
            ),
            Self::MissingColumn {
                path,
                name,
                available,
            } => {
                write!(
                    f,
                    "{}: no column `{name}`; columns: {available}",
                    path.display()
                )
            }
        }
    }
}

impl std::error::Error for CsvError {}

/// Columns of equal length with unit-suffixed names.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    /// Where it came from (empty for in-memory tables).
    pub path: PathBuf,
    /// Column names, e.g. `t_s`.
    pub names: Vec<String>,
    /// Column data.
    pub columns: Vec<Vec<f64>>,
}

impl Table {
    /// True when a column of that name exists.
    pub fn has(&self, name: &str) -> bool {
        self.names.iter().any(|n| n == name)
    }
    /// Column by name.
    pub fn column(&self, name: &str) -> Result<&[f64], CsvError> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| self.columns[i].as_slice())
            .ok_or_else(|| CsvError::MissingColumn {
                path: self.path.clone(),
                name: name.into(),
                available: self.names.join(", "),
            })
    }
    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.columns.first().map_or(0, Vec::len)
    }
}

fn has_unit(name: &str) -> bool {
    unit_of(name).is_some()
}

/// Reads a CSV file written by [`write_csv`] (comma separated, header first, `#` comment lines
/// skipped, a leading byte-order mark skipped).
pub fn read_csv(path: &Path) -> Result<Table, CsvError> {
    read_rows(path).map(|rows| rows.table)
}

/// Parses CSV text; `path` is only used in error messages.
pub fn parse_csv(path: &Path, text: &str) -> Result<Table, CsvError> {
    parse_rows(path, text).map(|rows| rows.table)
}

/// A table as read from its file, with the line each row came from, for errors that point at a
/// row.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Rows {
    /// The columns.
    pub table: Table,
    /// 1-based line of each row.
    pub lines: Vec<usize>,
}

/// [`read_csv`], keeping each row's line.
pub fn read_rows(path: &Path) -> Result<Rows, CsvError> {
    let text = fs::read_to_string(path).map_err(|e| CsvError::Io {
        path: path.into(),
        message: e.to_string(),
    })?;
    parse_rows(path, &text)
}

/// [`parse_csv`], keeping each row's line.
pub fn parse_rows(path: &Path, text: &str) -> Result<Rows, CsvError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
    let (_, header) = lines.next().ok_or(CsvError::Empty { path: path.into() })?;
    let names: Vec<String> = header.split(',').map(|s| s.trim().to_string()).collect();
    for (i, n) in names.iter().enumerate() {
        if !has_unit(n) {
            return Err(CsvError::NoUnit {
                path: path.into(),
                column: i + 1,
                name: n.clone(),
            });
        }
    }
    let mut columns = vec![Vec::new(); names.len()];
    let mut row_lines = Vec::new();
    for (idx, line) in lines {
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != names.len() {
            return Err(CsvError::WrongCellCount {
                path: path.into(),
                line: idx + 1,
                expected: names.len(),
                found: cells.len(),
            });
        }
        for (c, cell) in cells.iter().enumerate() {
            let v: f64 = cell
                .trim()
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| CsvError::BadNumber {
                    path: path.into(),
                    line: idx + 1,
                    column: c + 1,
                    name: names[c].clone(),
                    given: cell.trim().to_string(),
                })?;
            columns[c].push(v);
        }
        row_lines.push(idx + 1);
    }
    Ok(Rows {
        table: Table {
            path: path.into(),
            names,
            columns,
        },
        lines: row_lines,
    })
}

impl Rows {
    /// The 1-based column index of `name` and its samples.
    fn indexed(&self, name: &str) -> Result<(usize, &[f64]), CsvError> {
        let samples = self.table.column(name)?;
        let index = self.table.names.iter().position(|n| n == name).unwrap_or(0);
        Ok((index + 1, samples))
    }

    /// The line of row `row` (1-based; 0 for a row that does not exist).
    pub fn line(&self, row: usize) -> usize {
        self.lines.get(row).copied().unwrap_or(0)
    }

    /// The column `name` as a record's time base \[its unit\], checked as the module doc says:
    /// at least two samples, strictly increasing, a median step of at least
    /// [`MIN_SAMPLE_PERIOD_S`] (`factor` converts the column's unit to seconds) and every step
    /// within [`MAX_STEP_RATIO`] of the median. Errors name the file, the line and the column.
    pub fn time(&self, name: &str, factor: f64) -> Result<&[f64], CsvError> {
        let (column, t) = self.indexed(name)?;
        let fault = |row: usize, fault: TimeFault| CsvError::Time {
            path: self.table.path.clone(),
            line: self.line(row).max(1),
            column,
            name: name.into(),
            fault,
        };
        if t.len() < 2 {
            return Err(fault(
                t.len().saturating_sub(1),
                TimeFault::TooShort { samples: t.len() },
            ));
        }
        if let Some(k) = (1..t.len()).find(|&k| !(t[k] > t[k - 1])) {
            return Err(fault(
                k,
                TimeFault::NotIncreasing {
                    previous_s: t[k - 1] * factor,
                    previous_line: self.line(k - 1),
                    given_s: t[k] * factor,
                },
            ));
        }
        let steps: Vec<f64> = t.windows(2).map(|w| (w[1] - w[0]) * factor).collect();
        let mut sorted = steps.clone();
        sorted.sort_by(f64::total_cmp);
        let median_s = sorted[sorted.len() / 2];
        if !(median_s >= MIN_SAMPLE_PERIOD_S) {
            return Err(fault(1, TimeFault::TooFine { median_s }));
        }
        let uneven = steps
            .iter()
            .position(|&s| !(s <= MAX_STEP_RATIO * median_s && s * MAX_STEP_RATIO >= median_s));
        if let Some(i) = uneven {
            return Err(fault(
                i + 1,
                TimeFault::Uneven {
                    step_s: steps[i],
                    previous_line: self.line(i),
                    median_s,
                },
            ));
        }
        Ok(t)
    }

    /// The column `name` times `factor` (its unit to SI), every value finite also in the f32 the
    /// core computes in; errors name the file, the line and the column.
    pub fn f32_column(&self, name: &str, factor: f64) -> Result<Vec<f64>, CsvError> {
        let (column, values) = self.indexed(name)?;
        values
            .iter()
            .enumerate()
            .map(|(row, &v)| {
                let si = v * factor;
                if (si as f32).is_finite() {
                    Ok(si)
                } else {
                    Err(CsvError::BeyondF32 {
                        path: self.table.path.clone(),
                        line: self.line(row),
                        column,
                        name: name.into(),
                        given: v,
                    })
                }
            })
            .collect()
    }
}

/// Writes columns (all of the same length) with a header; values in Rust's shortest round-trip format.
pub fn write_csv(path: &Path, table: &Table) -> Result<(), CsvError> {
    let io = |e: std::io::Error| CsvError::Io {
        path: path.into(),
        message: e.to_string(),
    };
    for (i, n) in table.names.iter().enumerate() {
        if !has_unit(n) {
            return Err(CsvError::NoUnit {
                path: path.into(),
                column: i + 1,
                name: n.clone(),
            });
        }
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        fs::create_dir_all(dir).map_err(io)?;
    }
    let mut out = std::io::BufWriter::new(fs::File::create(path).map_err(io)?);
    writeln!(out, "{}", table.names.join(",")).map_err(io)?;
    for r in 0..table.rows() {
        let mut first = true;
        for c in &table.columns {
            if !first {
                write!(out, ",").map_err(io)?;
            }
            first = false;
            write!(out, "{}", c[r]).map_err(io)?;
        }
        writeln!(out).map_err(io)?;
    }
    out.flush().map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_two_axis() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("xy.csv");
        let t = Table {
            path: PathBuf::new(),
            names: vec![
                "t_s".into(),
                "ux_V".into(),
                "uy_V".into(),
                "x_m".into(),
                "y_m".into(),
            ],
            columns: vec![
                vec![0.0, 1e-3],
                vec![1.0, 2.0],
                vec![3.0, 4.5],
                vec![1.5e-6, 2.25e-6],
                vec![0.1, -0.2],
            ],
        };
        write_csv(&p, &t).unwrap();
        let r = read_csv(&p).unwrap();
        assert_eq!(r.names, t.names);
        assert_eq!(r.columns, t.columns);
        assert_eq!(r.column("uy_V").unwrap(), &[3.0, 4.5]);
        let e = r.column("z_m").unwrap_err().to_string();
        assert!(e.contains("z_m") && e.contains("ux_V"), "{e}");
    }

    #[test]
    fn errors_name_file_line_column() {
        let p = Path::new("data.csv");
        let e = parse_csv(p, "t_s,u_V\n0,1\n1e-3,abc\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("data.csv:3")
                && e.contains("column 2")
                && e.contains("u_V")
                && e.contains("abc"),
            "{e}"
        );
        let e = parse_csv(p, "t_s,u\n").unwrap_err().to_string();
        assert!(e.contains("column 2") && e.contains("unit"), "{e}");
        let e = parse_csv(p, "t_s,u_V\n0\n").unwrap_err().to_string();
        assert!(e.contains("data.csv:2") && e.contains("expected 2"), "{e}");
        let e = read_csv(Path::new("/nonexistent/x.csv"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/x.csv"), "{e}");
        for cell in ["NaN", "inf", "-inf", "1e309"] {
            let e = parse_csv(p, &format!("t_s,u_V\n0,1\n1e-3,{cell}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("data.csv:3") && e.contains("column 2"), "{e}");
        }
    }

    #[test]
    fn a_byte_order_mark_is_skipped() {
        let t = parse_csv(Path::new("bom.csv"), "\u{feff}t_s,u_V\n0,1\n").unwrap();
        assert_eq!(t.names, ["t_s", "u_V"]);
        assert_eq!(t.column("t_s").unwrap(), &[0.0]);
    }

    /// The time column's error for `times` (a `# comment` line first, so lines are not rows).
    fn time_error(times: &[f64]) -> String {
        let mut text = String::from("# a record\nu_V,t_s\n");
        for t in times {
            text.push_str(&format!("0,{t}\n"));
        }
        let rows = parse_rows(Path::new("rec.csv"), &text).unwrap();
        rows.time("t_s", 1.0).unwrap_err().to_string()
    }

    #[test]
    fn time_columns_are_uniform_sampling_time_bases() {
        let uniform: Vec<f64> = (0..20).map(|k| f64::from(k) * 0.1).collect();
        let text: String = uniform.iter().map(|t| format!("{t},1\n")).collect();
        let rows = parse_rows(Path::new("ok.csv"), &format!("t_s,u_V\n{text}")).unwrap();
        assert_eq!(rows.time("t_s", 1.0).unwrap(), uniform.as_slice());
        assert_eq!(rows.line(3), 5);
        // Reversed: the second sample (line 4) is not after the first.
        let e = time_error(&[3.0, 2.0, 1.0]);
        assert!(
            e.contains("rec.csv:4: column 2 (`t_s`)")
                && e.contains("not after")
                && e.contains("line 3"),
            "{e}"
        );
        // Constant.
        let e = time_error(&[5.0, 5.0, 5.0]);
        assert!(e.contains("rec.csv:4") && e.contains("strictly"), "{e}");
        // Tiny: 1e-15 s steps.
        let e = time_error(&[0.0, 1e-15, 2e-15, 3e-15]);
        assert!(
            e.contains("rec.csv:4") && e.contains("median step is 1.000e-15 s"),
            "{e}"
        );
        // A gap after the fifth sample (line 7 → 8), and a doubled sample.
        let mut gap: Vec<f64> = (0..10).map(f64::from).collect();
        gap[5..].iter_mut().for_each(|t| *t += 0.6);
        let e = time_error(&gap);
        assert!(
            e.contains("rec.csv:8") && e.contains("from line 7") && e.contains("1.600 times"),
            "{e}"
        );
        let mut doubled: Vec<f64> = (0..10).map(f64::from).collect();
        doubled.insert(4, 3.5);
        let e = time_error(&doubled);
        assert!(e.contains("rec.csv:7") && e.contains("0.500 times"), "{e}");
        // One sample.
        let e = time_error(&[0.0]);
        assert!(e.contains("at least two"), "{e}");
        // Jitter within 1.5x passes.
        let jitter: Vec<f64> = (0..10)
            .map(|k| f64::from(k) + 0.2 * f64::from(k % 2))
            .collect();
        assert!(parse_rows(
            Path::new("j.csv"),
            &format!(
                "t_s,u_V\n{}",
                jitter
                    .iter()
                    .map(|t| format!("{t},0\n"))
                    .collect::<String>()
            )
        )
        .unwrap()
        .time("t_s", 1.0)
        .is_ok());
    }

    #[test]
    fn values_beyond_f32_are_refused_with_their_line() {
        let rows = parse_rows(Path::new("big.csv"), "t_s,u_V,y_nm\n0,1,1e300\n1,1e39,2\n").unwrap();
        let e = rows.f32_column("u_V", 1.0).unwrap_err().to_string();
        assert!(
            e.contains("big.csv:3: column 2 (`u_V`)") && e.contains("f32"),
            "{e}"
        );
        // 1e300 nm = 1e291 m is still beyond f32; 2 nm converts.
        let e = rows.f32_column("y_nm", 1e-9).unwrap_err().to_string();
        assert!(e.contains("big.csv:2: column 3"), "{e}");
        let rows = parse_rows(Path::new("ok.csv"), "t_s,y_nm\n0,1e30\n").unwrap();
        assert_eq!(rows.f32_column("y_nm", 1e-9).unwrap(), [1e30 * 1e-9]);
    }
}
