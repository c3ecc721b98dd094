//! The shell command blocks of a README, as `tests/readme_commands.rs` runs them.
//!
//! A fenced block (```` ``` ```` or `~~~`, indented at most three spaces) is a *command block*
//! when its info string's first word is `sh`, `bash`, `shell` or `console`. Its commands are
//! its lines as written; in a `console` block only the lines after a `$ ` prompt (and the
//! `> ` continuation lines after them) are commands, the rest is output. A block with another
//! language (`text`, `toml`, `rust`, ...) is not run. A fence without a language is an error:
//! it must say whether it holds commands (`sh`) or not (`text`).
//!
//! The line right before a command block's opening fence may be a marker, an HTML comment
//! that says how the block runs (blank lines are not allowed in between):
//!
//! ```text
//! <!-- run: dir=firmware qemu long source=tests/readme/qemu-link-session.sh -->
//! <!-- run: skip=flashes a board over probe-rs and talks to its USB serial device -->
//! ```
//!
//! - `dir=PATH`: the folder it runs from, relative to the repository root (default: the root);
//! - `qemu`: it needs `qemu-system-arm` and the Cortex-M target (skipped with a note without);
//! - `long`: it takes more than about 30 s (run by the `#[ignore]`d test);
//! - `source=PATH`: a script (relative to the root) sourced before the block, in the block's
//!   folder: the state the README's text assumes (e.g. a running image and `$L` from the block
//!   before);
//! - `skip=REASON`: the block cannot run in a test (a real board, a serial device); the rest of
//!   the comment is the reason, and the test lists the block.
//!
//! A marker that is not before a command block, an unknown word, or a missing reason is an
//! error naming the file and line.

/// How a command block runs, from its marker.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Marker {
    /// Folder it runs from, relative to the repository root ("" for the root).
    pub dir: String,
    /// Needs QEMU and the Cortex-M target.
    pub qemu: bool,
    /// Takes more than about 30 s.
    pub long: bool,
    /// Script sourced before the block (relative to the root).
    pub source: Option<String>,
    /// Why the block cannot run in a test.
    pub skip: Option<String>,
}

/// One command block.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Block {
    /// Line of the opening fence (1-based).
    pub line: usize,
    /// The block's language (`sh`, `bash`, `shell`, `console`).
    pub language: String,
    /// The commands, one line each, as written (prompts of a `console` block removed).
    pub script: String,
    /// Its marker (the default when it has none).
    pub marker: Marker,
}

const COMMAND_LANGUAGES: [&str; 4] = ["sh", "bash", "shell", "console"];
const MARKER_START: &str = "<!-- run:";

/// Parses a marker comment's words (`line` is `<!-- run: ... -->`, trimmed).
fn parse_marker(text: &str, file: &str, line: usize) -> Result<Marker, String> {
    let body = text
        .strip_prefix(MARKER_START)
        .and_then(|rest| rest.strip_suffix("-->"))
        .ok_or_else(|| {
            format!("{file}:{line}: a marker is one line, `<!-- run: WORDS -->`: {text}")
        })?
        .trim();
    let mut marker = Marker::default();
    let mut rest = body;
    while !rest.is_empty() {
        if let Some(reason) = rest.strip_prefix("skip=") {
            let reason = reason.trim();
            if reason.is_empty() {
                return Err(format!("{file}:{line}: `skip=` needs a reason"));
            }
            marker.skip = Some(reason.to_string());
            break;
        }
        let (word, after) = rest.split_once(char::is_whitespace).unwrap_or((rest, ""));
        rest = after.trim_start();
        match word.split_once('=') {
            None if word == "qemu" => marker.qemu = true,
            None if word == "long" => marker.long = true,
            Some(("dir", d)) if !d.is_empty() => marker.dir = d.trim_end_matches('/').to_string(),
            Some(("source", s)) if !s.is_empty() => marker.source = Some(s.to_string()),
            _ => {
                return Err(format!(
                    "{file}:{line}: unknown marker word `{word}` (known: dir=PATH, qemu, long, \
                     source=PATH, skip=REASON)"
                ))
            }
        }
    }
    if marker.dir.starts_with('/') || marker.dir.split('/').any(|p| p == "..") {
        return Err(format!(
            "{file}:{line}: dir={} must be a folder inside the repository",
            marker.dir
        ));
    }
    Ok(marker)
}

/// A fence line's marker characters (```` ``` ```` or `~~~`, three or more) and info string.
fn fence(line: &str) -> Option<(char, usize, &str)> {
    let indent = line.len() - line.trim_start_matches(' ').len();
    if indent > 3 {
        return None;
    }
    let rest = &line[indent..];
    let c = rest.chars().next().filter(|c| *c == '`' || *c == '~')?;
    let n = rest.chars().take_while(|x| *x == c).count();
    (n >= 3).then(|| (c, n, rest[n..].trim()))
}

/// The commands of a block's lines: as written, or a `console` block's prompted lines.
fn commands(language: &str, lines: &[&str]) -> String {
    if language != "console" {
        return lines.iter().map(|l| format!("{l}\n")).collect();
    }
    let mut out = String::new();
    let mut continued = false;
    for l in lines {
        let t = l.trim_start();
        if let Some(command) = t.strip_prefix("$ ") {
            out.push_str(command);
            out.push('\n');
            continued = command.trim_end().ends_with('\\');
        } else if let Some(more) = t.strip_prefix("> ").filter(|_| continued) {
            out.push_str(more);
            out.push('\n');
            continued = more.trim_end().ends_with('\\');
        } else {
            continued = false;
        }
    }
    out
}

/// Every command block of the markdown `text` (named `file` in errors), in order. Errors: a
/// fence without a language, a marker that is not right before a command block, a bad marker,
/// a block that is never closed.
pub fn command_blocks(text: &str, file: &str) -> Result<Vec<Block>, String> {
    let lines: Vec<&str> = text.lines().collect();
    let mut blocks = Vec::new();
    let mut pending: Option<(usize, Marker)> = None;
    let mut i = 0;
    while i < lines.len() {
        let number = i + 1;
        let line = lines[i];
        let trimmed = line.trim();
        if trimmed.starts_with(MARKER_START) {
            if let Some((at, _)) = pending {
                return Err(format!(
                    "{file}:{at}: marker not followed by a command block"
                ));
            }
            pending = Some((number, parse_marker(trimmed, file, number)?));
            i += 1;
            continue;
        }
        let Some((c, n, info)) = fence(line) else {
            if let Some((at, _)) = pending.take() {
                return Err(format!(
                    "{file}:{at}: marker not right before a command block's fence"
                ));
            }
            i += 1;
            continue;
        };
        let language = info.split_whitespace().next().unwrap_or("").to_string();
        if language.is_empty() {
            return Err(format!(
                "{file}:{number}: fence without a language: `sh` (or bash, console) for commands, \
                 `text` for anything else"
            ));
        }
        let close = lines[i + 1..]
            .iter()
            .position(|l| {
                fence(l).is_some_and(|(cc, nn, rest)| cc == c && nn >= n && rest.is_empty())
            })
            .map(|p| i + 1 + p)
            .ok_or_else(|| format!("{file}:{number}: block never closed"))?;
        let marker = pending.take();
        if COMMAND_LANGUAGES.contains(&language.as_str()) {
            blocks.push(Block {
                line: number,
                script: commands(&language, &lines[i + 1..close]),
                language,
                marker: marker.map(|(_, m)| m).unwrap_or_default(),
            });
        } else if let Some((at, _)) = marker {
            return Err(format!(
                "{file}:{at}: marker before a `{language}` block, which is not run"
            ));
        }
        i = close + 1;
    }
    if let Some((at, _)) = pending {
        return Err(format!("{file}:{at}: marker at the end of the file"));
    }
    Ok(blocks)
}
