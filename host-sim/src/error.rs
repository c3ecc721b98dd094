//! host-sim's one error type: what kind of failure a command or helper met, and the text the
//! command line prints after `error: ` (the same text the Python package raises).
//!
//! A variant says what failed — an option refused ([`Error::Usage`]), a file that could not be
//! read or written ([`Error::Read`], [`Error::Write`]), a record whose content is refused
//! ([`Error::Data`]), the stage file or the core refusing a set ([`Error::Stage`],
//! [`Error::Params`]), the firmware's link ([`Error::Link`]), a fit or a set refused
//! ([`Error::Fit`], [`Error::Refused`]) — and carries the cause where there is one, so
//! [`std::error::Error::source`] reaches the io, stage or core error.

use piezo_core::ParamError;
use piezo_stage::StageError;
use std::path::PathBuf;
use std::sync::Arc;

/// host-sim's result.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Why a host-sim command or helper failed. `Display` is the message the command line prints.
///
/// `Clone` (io and JSON errors behind an `Arc`) so that a result can be kept in a report.
#[derive(Debug, Clone, thiserror::Error)]
pub enum Error {
    /// An option, or a combination of options, refused.
    #[error("{0}")]
    Usage(String),
    /// A file that could not be read: `FLAG PATH: cause` (`PATH: cause` without a flag).
    #[error("{}{}: {source}", lead(flag, " "), path.display())]
    Read {
        /// The option that named the file (`--fit-report`), or empty.
        flag: &'static str,
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: Arc<std::io::Error>,
    },
    /// A file or folder that could not be written: `FLAG PATH: cause` (`PATH: cause` without a flag).
    #[error("{}{}: {source}", lead(flag, " "), path.display())]
    Write {
        /// The option that named the file (`--out`), or empty.
        flag: &'static str,
        /// The file or folder.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: Arc<std::io::Error>,
    },
    /// A record, log or CSV whose content is refused; the text names the file, line and column
    /// where they are known.
    #[error("{0}")]
    Data(String),
    /// A stage file refused (read, parsed or checked): `CONTEXT: ` and piezo-stage's located text.
    #[error("{}{source}", lead(context, ": "))]
    Stage {
        /// What was being read (`--stage`), or empty.
        context: String,
        /// piezo-stage's error.
        #[source]
        source: Box<StageError>,
    },
    /// A parameter set piezo-core refused: `CONTEXT: ` and the core's text.
    #[error("{}{source}", lead(context, ": "))]
    Params {
        /// What was being built (`piezo-core refused the x axis set`), or empty.
        context: String,
        /// piezo-core's error.
        #[source]
        source: ParamError,
    },
    /// The firmware's command link failed: no connection, a frame refused, an answer not expected.
    #[error("{0}")]
    Link(String),
    /// A fit that found nothing, or whose result is not usable.
    #[error("{0}")]
    Fit(String),
    /// A set, a servo or a step refused by a check (the stage file's, the firmware's or host-sim's).
    #[error("{0}")]
    Refused(String),
    /// An input or output error whose file the surrounding text names.
    #[error("{0}")]
    Io(#[source] Arc<std::io::Error>),
    /// The drawing library's failure, in its words.
    #[error("{0}")]
    Draw(String),
    /// A figure that could not be drawn or written.
    #[error(transparent)]
    Plot(Box<crate::plot::PlotError>),
    /// An identification that failed.
    #[error(transparent)]
    Identify(Box<crate::identify::IdentifyError>),
    /// A close-loop run that failed.
    #[error(transparent)]
    CloseLoop(Box<crate::close_loop::CloseLoopError>),
    /// A firmware log that could not be captured.
    #[error(transparent)]
    Capture(Box<crate::capture::CaptureError>),
    /// A CSV file the reference reader refused.
    #[error(transparent)]
    Csv(Box<crate::csv::CsvError>),
    /// A signal specification refused.
    #[error(transparent)]
    Signal(Box<crate::signal::SignalError>),
    /// An effect specification refused.
    #[error(transparent)]
    Effect(Box<crate::effects::EffectError>),
    /// A plant refused.
    #[error(transparent)]
    Plant(Box<crate::plant::PlantError>),
    /// A simulation of the reference plants that failed.
    #[error(transparent)]
    Sim(Box<crate::sim::SimError>),
    /// The reference's integrator failed.
    #[error(transparent)]
    Ode(Box<crate::ode::OdeError>),
    /// A value that could not be turned into JSON (or JSON that could not be read).
    #[error("{0}")]
    Json(#[source] Arc<serde_json::Error>),
    /// A worker thread that panicked: what it was doing.
    #[error("{0} panicked")]
    Panicked(&'static str),
    /// An error met while doing something the text names first: `CONTEXT: error`.
    #[error("{context}: {source}")]
    In {
        /// What was being done (`--data`, `axis x`).
        context: String,
        /// The error.
        #[source]
        source: Box<Error>,
    },
}

/// `text` and `separator`, or nothing when `text` is empty.
fn lead(text: &str, separator: &str) -> String {
    if text.is_empty() {
        String::new()
    } else {
        format!("{text}{separator}")
    }
}

impl Error {
    /// A file that could not be read, named as `FLAG PATH` (or `PATH` when `flag` is empty).
    pub fn read(
        flag: &'static str,
        path: impl Into<PathBuf>,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Read {
            flag,
            path,
            source: Arc::new(source),
        }
    }

    /// A file or folder that could not be written, named as `FLAG PATH` (or `PATH`).
    pub fn write(
        flag: &'static str,
        path: impl Into<PathBuf>,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Write {
            flag,
            path,
            source: Arc::new(source),
        }
    }

    /// This error behind `context: ` (`--data: ...`).
    pub fn context(self, context: impl Into<String>) -> Self {
        Self::In {
            context: context.into(),
            source: Box::new(self),
        }
    }

    /// A stage file refused, behind `context: ` (or alone when `context` is empty).
    pub fn stage(context: impl Into<String>) -> impl FnOnce(StageError) -> Self {
        let context = context.into();
        move |source| Self::Stage {
            context,
            source: Box::new(source),
        }
    }

    /// A set piezo-core refused, behind `context: ` (or alone when `context` is empty).
    pub fn params(context: impl Into<String>) -> impl FnOnce(ParamError) -> Self {
        let context = context.into();
        move |source| Self::Params { context, source }
    }
}

impl From<StageError> for Error {
    fn from(source: StageError) -> Self {
        Self::Stage {
            context: String::new(),
            source: Box::new(source),
        }
    }
}

impl From<ParamError> for Error {
    fn from(source: ParamError) -> Self {
        Self::Params {
            context: String::new(),
            source,
        }
    }
}

impl From<std::io::Error> for Error {
    fn from(source: std::io::Error) -> Self {
        Self::Io(Arc::new(source))
    }
}

impl From<serde_json::Error> for Error {
    fn from(source: serde_json::Error) -> Self {
        Self::Json(Arc::new(source))
    }
}

/// `From` for the errors kept behind a `Box` (so that `Result<T, Error>` stays small).
macro_rules! from_boxed {
    ($($variant:ident($source:ty)),* $(,)?) => {$(
        impl From<$source> for Error {
            fn from(source: $source) -> Self {
                Self::$variant(Box::new(source))
            }
        }
    )*};
}

from_boxed!(
    Plot(crate::plot::PlotError),
    Identify(crate::identify::IdentifyError),
    CloseLoop(crate::close_loop::CloseLoopError),
    Capture(crate::capture::CaptureError),
    Csv(crate::csv::CsvError),
    Signal(crate::signal::SignalError),
    Effect(crate::effects::EffectError),
    Plant(crate::plant::PlantError),
    Sim(crate::sim::SimError),
    Ode(crate::ode::OdeError),
);

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    fn not_found() -> std::io::Error {
        std::io::Error::new(std::io::ErrorKind::NotFound, "No such file or directory")
    }

    #[test]
    fn display_is_the_text_the_command_line_prints() {
        let read = Error::read("--fit-report", "out/a.json")(not_found());
        assert_eq!(
            read.to_string(),
            "--fit-report out/a.json: No such file or directory"
        );
        let write = Error::write("", "out/b.csv")(not_found());
        assert_eq!(write.to_string(), "out/b.csv: No such file or directory");
        assert_eq!(
            Error::Usage("--x-freq: must be positive".into()).to_string(),
            "--x-freq: must be positive"
        );
        assert_eq!(
            Error::Data("r.csv:3: column 2 (u_V): `x` is not a number".into()).to_string(),
            "r.csv:3: column 2 (u_V): `x` is not a number"
        );
        let params = ParamError::NonFinite { field: "beta" };
        assert_eq!(
            Error::params("piezo-core refused the x axis set")(params).to_string(),
            format!("piezo-core refused the x axis set: {params}")
        );
        assert_eq!(Error::from(params).to_string(), params.to_string());
        let stage = StageError::new(
            "s.toml",
            piezo_stage::StageErrorKind::Invalid,
            "x.model",
            "refused".to_string(),
        );
        assert_eq!(
            Error::stage("--stage")(stage.clone()).to_string(),
            format!("--stage: {stage}")
        );
        assert_eq!(Error::from(stage.clone()).to_string(), stage.to_string());
        assert_eq!(
            Error::Link("no answer".into())
                .context("link status")
                .to_string(),
            "link status: no answer"
        );
        assert_eq!(
            Error::Panicked("plant run").to_string(),
            "plant run panicked"
        );
    }

    #[test]
    fn source_reaches_the_cause() {
        let read = Error::read("--data", "r.csv")(not_found());
        // The io error is shared behind an `Arc` (so that `Error` is `Clone`).
        let io = read.source().unwrap().downcast_ref::<Arc<std::io::Error>>();
        assert_eq!(io.unwrap().kind(), std::io::ErrorKind::NotFound);
        let write = Error::write("--out", "o.csv")(not_found());
        assert!(write.source().unwrap().is::<Arc<std::io::Error>>());
        let params = ParamError::NonFinite { field: "gamma" };
        let e = Error::params("x")(params);
        assert_eq!(
            e.source().unwrap().downcast_ref::<ParamError>(),
            Some(&params)
        );
        let stage = StageError::new(
            "s.toml",
            piezo_stage::StageErrorKind::Syntax,
            "",
            "not TOML".to_string(),
        );
        // The stage error is kept behind a `Box` (so that `Result<T, Error>` stays small).
        let e = Error::from(stage.clone());
        let source = e.source().unwrap().downcast_ref::<Box<StageError>>();
        assert_eq!(source.map(|b| &**b), Some(&stage));
        let e = Error::from(stage.clone()).context("--params");
        let inner = e.source().unwrap().downcast_ref::<Box<Error>>().unwrap();
        assert!(inner.source().unwrap().is::<Box<StageError>>());
        assert!(Error::Usage("--low".into()).source().is_none());
    }
}
