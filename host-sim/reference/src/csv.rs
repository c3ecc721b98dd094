//! CSV files of sampled signals; every column name carries its unit as a suffix (`t_s`, `u_V`, `y_m`,
//! `ux_V`, `uy_V`, `x_m`, ...). A two-axis file holds both axes as separate columns.
//! Reader errors name the file, the line (1-based) and the column (1-based and by name).

use std::fmt;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Units accepted as column suffixes.
pub const UNITS: &[&str] = &[
    "s", "V", "m", "mm", "um", "nm", "N", "Hz", "V_per_s", "m_per_s", "1",
];

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

impl fmt::Display for CsvError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::Empty { path } => write!(f, "{}: empty file, expected a header line", path.display()),
            Self::NoUnit { path, column, name } => write!(
                f,
                "{}:1: column {column} `{name}` has no unit suffix (expected name_UNIT with UNIT one of {})",
                path.display(),
                UNITS.join(", ")
            ),
            Self::BadNumber { path, line, column, name, given } => write!(
                f,
                "{}:{line}: column {column} (`{name}`): `{given}` is not a finite number",
                path.display()
            ),
            Self::WrongCellCount { path, line, expected, found } => {
                write!(f, "{}:{line}: expected {expected} cells, found {found}", path.display())
            }
            Self::MissingColumn { path, name, available } => {
                write!(f, "{}: no column `{name}`; columns: {available}", path.display())
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
    UNITS.iter().any(|u| {
        name.len() > u.len() + 1 && name.ends_with(u) && name[..name.len() - u.len()].ends_with('_')
    })
}

/// Reads a CSV file written by [`write_csv`] (comma separated, header first, `#` comment lines skipped).
pub fn read_csv(path: &Path) -> Result<Table, CsvError> {
    let text = fs::read_to_string(path).map_err(|e| CsvError::Io {
        path: path.into(),
        message: e.to_string(),
    })?;
    parse_csv(path, &text)
}

/// Parses CSV text; `path` is only used in error messages.
pub fn parse_csv(path: &Path, text: &str) -> Result<Table, CsvError> {
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
    }
    Ok(Table {
        path: path.into(),
        names,
        columns,
    })
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
    }
}
