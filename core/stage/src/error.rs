//! Errors that name the file, the line and column, and the key path (`x.bouc_wen.gamma`).

use piezo_core::ParamError;
use std::fmt;

/// What went wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageErrorKind {
    /// The file could not be read or written.
    Io,
    /// Not TOML, or not the stage file's schema (unknown key, missing key, wrong type).
    Syntax,
    /// A value the core (or the io chain check) refused.
    Invalid,
}

/// An error in a stage file.
#[derive(Debug, Clone, PartialEq)]
pub struct StageError {
    /// The file.
    pub file: String,
    /// 1-based line, when known.
    pub line: Option<usize>,
    /// 1-based column, when known.
    pub column: Option<usize>,
    /// The key path (`x.bouc_wen.gamma`; empty for the whole file).
    pub key: String,
    /// What went wrong.
    pub kind: StageErrorKind,
    /// The reason, in words.
    pub message: String,
    /// The core's refusal, when the core refused the value.
    pub core: Option<ParamError>,
}

impl fmt::Display for StageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
            if let Some(column) = self.column {
                write!(f, ":{column}")?;
            }
        }
        if self.key.is_empty() {
            write!(f, ": {}", self.message)
        } else {
            write!(f, ": `{}`: {}", self.key, self.message)
        }
    }
}

impl std::error::Error for StageError {}

/// 1-based (line, column) of a byte offset.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(text.len());
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let column = before.rfind('\n').map_or(offset, |i| offset - i - 1) + 1;
    (line, column)
}

impl StageError {
    /// An error without a location yet (see [`StageError::located`]).
    pub fn new(file: &str, kind: StageErrorKind, key: &str, message: String) -> Self {
        Self {
            file: file.into(),
            line: None,
            column: None,
            key: key.into(),
            kind,
            message,
            core: None,
        }
    }

    /// A core refusal of the value at `key`.
    pub fn core(key: &str, e: ParamError) -> Self {
        let mut err = Self::new(
            "",
            StageErrorKind::Invalid,
            key,
            format!("refused by piezo-core: {e}"),
        );
        err.core = Some(e);
        err
    }

    pub(crate) fn io(file: &str, e: std::io::Error) -> Self {
        Self::new(file, StageErrorKind::Io, "", e.to_string())
    }

    pub(crate) fn toml(file: &str, text: &str, e: &toml::de::Error, path: Option<String>) -> Self {
        let (line, column) = match e.span() {
            Some(span) => {
                let (l, c) = line_column(text, span.start);
                (Some(l), Some(c))
            }
            None => (None, None),
        };
        let key = path.filter(|p| p != ".").unwrap_or_default();
        Self {
            file: file.into(),
            line,
            column,
            key,
            kind: StageErrorKind::Syntax,
            message: e.message().trim().to_string(),
            core: None,
        }
    }

    /// The error with its file name and, when the key is found in `text`, its line and column.
    pub fn located(mut self, file: &str, text: &str) -> Self {
        self.file = file.into();
        if self.line.is_none() {
            if let Some(offset) = find_key(text, &self.key) {
                let (l, c) = line_column(text, offset);
                self.line = Some(l);
                self.column = Some(c);
            }
        }
        self
    }
}

/// Byte offset of `a.b.key` in a TOML text written with `[a.b]` headers (or of the header `[a.b]`
/// itself, or of a top-level key): the first line in that table that starts with `key`.
fn find_key(text: &str, path: &str) -> Option<usize> {
    if path.is_empty() {
        return None;
    }
    let path = path.split('[').next().unwrap_or(path);
    let (table, key) = match path.rsplit_once('.') {
        Some((t, k)) => (t, k),
        None => ("", path),
    };
    let mut current = String::new();
    let mut offset = 0;
    let mut table_start = None;
    for line in text.split_inclusive('\n') {
        let trimmed = line.trim();
        if let Some(header) = trimmed.strip_prefix('[').and_then(|h| h.split(']').next()) {
            current = header.trim().to_string();
            if current == path && table_start.is_none() {
                table_start = Some(offset + line.find('[').unwrap_or(0));
            }
        } else if current == table {
            let name = trimmed.split('=').next().unwrap_or("").trim();
            if name == key {
                return Some(offset + line.find(key).unwrap_or(0));
            }
        }
        offset += line.len();
    }
    table_start.or_else(|| {
        // The key is absent: point at its table's header.
        let header = format!("[{table}]");
        text.find(&header)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_keys_and_headers() {
        let text = "[stage]\nname = \"a\"\n\n[x.bouc_wen]\na = 1.0\ngamma = 2.0\n";
        assert_eq!(
            line_column(text, find_key(text, "x.bouc_wen.gamma").unwrap()),
            (6, 1)
        );
        assert_eq!(
            line_column(text, find_key(text, "x.bouc_wen").unwrap()),
            (4, 1)
        );
        assert_eq!(
            line_column(text, find_key(text, "x.bouc_wen.n").unwrap()),
            (4, 1)
        );
        assert_eq!(
            line_column(text, find_key(text, "stage.name").unwrap()),
            (2, 1)
        );
    }
}
