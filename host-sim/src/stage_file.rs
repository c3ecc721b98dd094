//! The stage file as the tools write it: `[stage]` and `[io]` carried over from an existing stage
//! file (`--stage FILE`), or made from the record with a placeholder io chain that covers the
//! output windows to be written; the axes from the fit. Reading, writing and validating are
//! `piezo_stage`'s; the verdict on a written file is the check `host-sim compensate` makes
//! ([`StageFile::load`], then [`crate::compensate::feedforward_axes`]).

use piezo_core::ParamError;
use piezo_stage::{Io, Stage, StageError, StageFile};
use std::path::Path;

/// The `[stage]` and `[io]` sections of a file about to be written: from `given` (an existing
/// stage file, read and validated) or, without one, named `name` at the record's rate
/// `record_rate_hz` with a placeholder io chain whose drive range covers `drive_range_v` \[V\]
/// (the output windows to be written; [`Io::placeholder_covering`]), said on stderr.
pub fn stage_and_io(
    given: Option<&Path>,
    name: &str,
    record_rate_hz: f64,
    drive_range_v: (f32, f32),
) -> crate::Result<(Stage, Io)> {
    match given {
        Some(path) => {
            let (file, _) =
                StageFile::load(path).map_err(|e| crate::Error::Usage(format!("--stage: {e}")))?;
            Ok((file.stage, file.io))
        }
        None => {
            let io = Io::placeholder_covering(drive_range_v);
            let (d0, d1) = io.chain().drive_range_v();
            let bipolar = if io.dac_range_v[0] < 0.0 {
                " (a bipolar DAC span, which the firmware's DAC8563 does not drive)"
            } else {
                ""
            };
            eprintln!(
                "note: [io] is a placeholder ({} {}-{} V{bipolar}, {} V/V amplifier: drive \
                 {d0}-{d1} V; {} ±10.24 V, 10 µm/V sensor) and the loop rate is the record's \
                 ({record_rate_hz:.6} Hz): pass --stage FILE to carry [stage] and [io] from your \
                 stage file",
                io.dac_part,
                io.dac_range_v[0],
                io.dac_range_v[1],
                io.amplifier_gain_v_per_v,
                io.adc_part,
            );
            Ok((
                Stage {
                    name: name.to_string(),
                    version: "1".into(),
                    loop_rate_hz: rate_of(record_rate_hz),
                },
                io,
            ))
        }
    }
}

/// A record's rate as a loop rate: rounded to 1 mHz, so that 1 / (mean sample period) reads as the
/// nominal rate (200 Hz, not 199.99999 Hz).
pub fn rate_of(record_rate_hz: f64) -> f32 {
    ((record_rate_hz * 1e3).round() / 1e3) as f32
}

/// Why the firmware's check refused a stage file; decides what the user is told to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RefusalKind {
    /// An output window beyond `io.dac_range_v × io.amplifier_gain_v_per_v`.
    IoWindow,
    /// A map the compensator cannot invert (`ParamError::NotInvertible`).
    NotInvertible,
    /// Anything else (the text says what).
    Other,
}

/// The firmware's verdict on a stage file: the check `host-sim compensate` makes before it runs a
/// file (`StageFile::load`: parsed and validated with the core's constructors at its loop rate, the
/// output windows inside the io chain's drive range; then the feed-forward axes).
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Accepted: the firmware builds it and `compensate` runs it.
    Accepted,
    /// A model family the firmware does not run (dynamic, oscillator): not checked further.
    NotRunByFirmware,
    /// Refused: why, and the check's message (file, line, key).
    Refused {
        /// What kind of refusal.
        kind: RefusalKind,
        /// The check's message.
        message: String,
    },
}

impl Verdict {
    /// The check of `file` as written at `path` (its text `text`): in memory when it could not be
    /// written, else read back from disk as `compensate` reads it.
    pub fn of(file: &StageFile, path: &Path, text: Option<&str>) -> Self {
        if !file.axes().iter().all(|(_, a)| a.model.runs_on_firmware()) {
            return Self::NotRunByFirmware;
        }
        let name = path.display().to_string();
        let refused = |e: StageError, text: &str| Self::Refused {
            kind: refusal_kind(&e),
            message: e.located(&name, text).to_string(),
        };
        let in_memory;
        let (file, valid, text) = match text {
            Some(text) => match StageFile::load(path) {
                Ok((file, valid)) => (file, valid, text),
                Err(e) => return refused(e, text),
            },
            None => {
                in_memory = file.to_toml("");
                match file.validate() {
                    Ok(valid) => (file.clone(), valid, in_memory.as_str()),
                    Err(e) => return refused(e, &in_memory),
                }
            }
        };
        match crate::compensate::feedforward_axes_of(&file, &valid, &name, text) {
            Ok(_) => Self::Accepted,
            Err(e) => Self::Refused {
                kind: RefusalKind::Other,
                message: e.to_string(),
            },
        }
    }

    /// Whether the firmware refuses the file.
    pub fn refused(&self) -> bool {
        matches!(self, Self::Refused { .. })
    }

    /// One line for the report and the summary.
    pub fn words(&self) -> String {
        match self {
            Self::Accepted => "accepted by the firmware's stage-file check".into(),
            Self::NotRunByFirmware => "a model family the firmware does not run (it runs symmetric and asymmetric static models)".into(),
            Self::Refused { message, .. } => {
                format!("REFUSED by the firmware's stage-file check: {message}")
            }
        }
    }

    /// One line for a summary that is followed by the refusal in full (`detailed`: false) or not.
    pub fn summary(&self, detailed: bool) -> String {
        match self {
            Self::Refused { .. } if !detailed => {
                "REFUSED by the firmware's stage-file check".into()
            }
            _ => self.words(),
        }
    }

    /// Short name for the report: `accepted`, `not-run-by-firmware`, `refused`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Accepted => "accepted",
            Self::NotRunByFirmware => "not-run-by-firmware",
            Self::Refused { .. } => "refused",
        }
    }

    /// What to do about a refusal, for a run with `invertible` (`--invertible` given) and `given`
    /// (`--stage`); `None` when accepted.
    pub fn remedy(&self, invertible: bool, given: Option<&Path>) -> Option<String> {
        let Self::Refused { kind, .. } = self else {
            return None;
        };
        Some(match (kind, given) {
            (RefusalKind::IoWindow, None) => "the placeholder [io] chain does not drive the \
                 output window: pass --stage FILE with your stage's real [io] (its DAC range and \
                 amplifier gain), or --allow-refused to keep the set anyway"
                .into(),
            (RefusalKind::IoWindow, Some(stage)) => format!(
                "the [io] chain of {} does not drive the output window the record needs: \
                 correct its io.dac_range_v or io.amplifier_gain_v_per_v if the record is right, \
                 or record within what it drives; --allow-refused keeps the set anyway",
                stage.display()
            ),
            (RefusalKind::NotInvertible, _) if !invertible => "pass --invertible to fit only \
                 sets the compensator accepts, or --allow-refused to keep it anyway"
                .into(),
            (RefusalKind::NotInvertible, _) => "no set the compensator accepts was found even \
                 with --invertible; --allow-refused keeps it anyway"
                .into(),
            (RefusalKind::Other, _) => "pass --allow-refused to keep it anyway".into(),
        })
    }
}

/// The kind of a refusal from the key and the core's error it carries.
fn refusal_kind(e: &StageError) -> RefusalKind {
    if matches!(e.core, Some(ParamError::NotInvertible { .. })) {
        RefusalKind::NotInvertible
    } else if matches!(e.core, Some(ParamError::WindowOutsideDrive { .. })) {
        RefusalKind::IoWindow
    } else {
        RefusalKind::Other
    }
}

/// A stage file written and checked.
#[derive(Debug, Clone, PartialEq)]
pub struct WrittenStage {
    /// Where it was (to be) written.
    pub path: String,
    /// Why it could not be written (`None`: written).
    pub not_written: Option<String>,
    /// The firmware's verdict on it.
    pub verdict: Verdict,
}

impl WrittenStage {
    /// The error a command returns for this file after everything else was written: the refusal
    /// with its remedy (unless `allow_refused`) and a failed write; `None` when there is none.
    pub fn error(
        &self,
        invertible: bool,
        given: Option<&Path>,
        allow_refused: bool,
    ) -> Option<String> {
        let mut out = Vec::new();
        if let Some(e) = &self.not_written {
            out.push(format!("--out {}: not written: {e}", self.path));
        }
        if let (Verdict::Refused { message, .. }, false) = (&self.verdict, allow_refused) {
            let remedy = self.verdict.remedy(invertible, given).unwrap_or_default();
            let what = if self.not_written.is_some() {
                "the set"
            } else {
                "the set written"
            };
            out.push(format!(
                "{what} to {} would be refused by the firmware: {message} ({remedy})",
                self.path
            ));
        }
        (!out.is_empty()).then(|| out.join("; "))
    }

    /// The written file named as the firmware names the set it runs
    /// ([`crate::identity::SetIdentity`]), on a line of its own; empty when it was not written.
    pub fn identity_line(&self) -> String {
        if self.not_written.is_some() {
            return String::new();
        }
        match crate::identity::SetIdentity::of_file(Path::new(&self.path)) {
            Ok(id) => format!("\nstage file: {id}"),
            Err(e) => format!("\nstage file: {e}"),
        }
    }

    /// The report's fields: `stage_file`, `stage_file_written`, `stage_file_not_written` and the
    /// verdict's ([`Verdict::report`]), for a run with `invertible` and `given`.
    pub fn report(&self, invertible: bool, given: Option<&Path>) -> StageFileReport<'_> {
        StageFileReport {
            stage_file: &self.path,
            stage_file_written: self.not_written.is_none(),
            stage_file_not_written: self.not_written.as_deref(),
            verdict: self.verdict.report(invertible, given),
        }
    }
}

impl Verdict {
    /// The report's fields of the verdict: `stage_file_check` (in words), `verdict` and `refusal`
    /// (the reason and remedy of a refusal, or null), for a run with `invertible` and `given`.
    pub fn report(&self, invertible: bool, given: Option<&Path>) -> VerdictReport<'_> {
        VerdictReport {
            stage_file_check: self.words(),
            verdict: self.name(),
            refusal: match self {
                Verdict::Refused { message, .. } => Some(RefusalReport {
                    reason: message,
                    remedy: self.remedy(invertible, given),
                }),
                _ => None,
            },
        }
    }
}

/// A written stage file in a report ([`WrittenStage::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StageFileReport<'a> {
    /// Where it was (to be) written.
    pub stage_file: &'a str,
    /// Whether it was written.
    pub stage_file_written: bool,
    /// Why it could not be written (null: written).
    pub stage_file_not_written: Option<&'a str>,
    /// The firmware's verdict on it, its fields beside these.
    #[serde(flatten)]
    pub verdict: VerdictReport<'a>,
}

/// The firmware's verdict in a report ([`Verdict::report`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VerdictReport<'a> {
    /// The verdict in words ([`Verdict::words`]).
    pub stage_file_check: String,
    /// `accepted`, `not-run-by-firmware` or `refused` ([`Verdict::name`]).
    pub verdict: &'static str,
    /// Why the set was refused and what to do (null unless refused).
    pub refusal: Option<RefusalReport<'a>>,
}

/// A refusal in a report: the check's message and the remedy ([`Verdict::remedy`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RefusalReport<'a> {
    /// The check's message.
    pub reason: &'a str,
    /// What to do about it.
    pub remedy: Option<String>,
}

/// The file as [`write_stage`] writes it (each axis's slew limit lowered where needed) and its
/// text with `header`, in memory.
pub fn stage_text(header: &str, file: &StageFile) -> (StageFile, String) {
    let file = with_feasible_slew(file);
    let text = file.to_toml(header);
    (file, text)
}

/// Writes `file` to `path` (with `header`) and checks it as `compensate` would read it; a file
/// that could not be written is checked in memory. Never fails: the outcome says what happened.
///
/// An axis's slew limit is lowered, where needed, to the fastest the core accepts at the file's
/// loop rate (a full-window move in `MIN_WINDOW_TICKS` ticks, a swing over the drive span in
/// `io_chain::MIN_DRIVE_TICKS`).
pub fn write_stage(path: &Path, header: &str, file: &StageFile) -> WrittenStage {
    let file = &with_feasible_slew(file);
    for note in slower_than_the_records(path, file) {
        eprintln!("note: {note}");
    }
    let written = file
        .write(path, header)
        .map_err(crate::Error::from)
        .and_then(|()| std::fs::read_to_string(path).map_err(crate::Error::from));
    let (text, not_written) = match written {
        Ok(text) => (Some(text), None),
        Err(e) => (None, Some(e.to_string())),
    };
    WrittenStage {
        path: path.display().to_string(),
        verdict: Verdict::of(file, path, text.as_deref()),
        not_written,
    }
}

/// For each axis with a rate-dependent gain whose slew limit is below the fastest command its
/// records reached (`identified.input_rate_max_v_per_s`): a note that its compensator follows a
/// command that fast only slew-limited, naming the file, the field and both speeds.
pub(crate) fn slower_than_the_records(path: &Path, file: &StageFile) -> Vec<String> {
    let mut notes = Vec::new();
    for (name, axis) in [("x", Some(&file.x)), ("y", file.y.as_ref())] {
        let Some(axis) = axis else { continue };
        let slew = axis.limits.slew_limit_v_per_s;
        let reached = axis
            .identified
            .as_ref()
            .and_then(|p| p.input_rate_max_v_per_s)
            .unwrap_or(0.0);
        if axis.effects.hysteresis_rate_gain_s_per_v > 0.0 && slew < reached {
            notes.push(format!(
                "{}: `{name}.limits.slew_limit_v_per_s` = {slew:.0} V/s, the fastest move at \
                 which the compensator can invert the rate-dependent gain \
                 (`{name}.effects.hysteresis_rate_gain_s_per_v`) over every state it reaches; \
                 the records reached {reached:.0} V/s, so a command that fast is followed only \
                 slew-limited",
                path.display()
            ));
        }
    }
    notes
}

/// `file` with each axis's slew limit lowered, where needed, to the fastest the core accepts at
/// the file's loop rate: what the DAC and amplifier chain can swing, and for a rate-dependent
/// gain the fastest move at which the compensator can invert it
/// ([`piezo_core::fastest_invertible_slew_v_per_s`]).
pub(crate) fn with_feasible_slew(file: &StageFile) -> StageFile {
    let mut file = file.clone();
    let period = 1.0 / file.stage.loop_rate_hz;
    let drive_fastest = file.io.chain().fastest_slew_v_per_s(period);
    let lower = |a: &mut piezo_stage::Axis| {
        let l = &mut a.limits;
        let fastest = piezo_core::CompensatorSettings {
            limits: *l,
            sample_period_s: period,
        }
        .fastest_slew_v_per_s();
        for fastest in [fastest, drive_fastest] {
            if fastest.is_finite() && fastest > 0.0 {
                l.slew_limit_v_per_s = l.slew_limit_v_per_s.min(fastest);
            }
        }
    };
    lower(&mut file.x);
    if let Some(y) = file.y.as_mut() {
        lower(y);
    }
    // A rate-dependent gain is invertible only up to the speed at which its one-step map stays
    // monotone over the states and gains it reaches: the slew limit is lowered to that speed.
    if let Ok(valid) = file.validate_with(piezo_stage::Check::Models) {
        for axis in &valid.axes {
            let piezo_stage::AxisChain::Static { model, .. } = axis.chain else {
                continue;
            };
            if !model.has_rate_gain() {
                continue;
            }
            let limits = if axis.name == "x" {
                &mut file.x.limits
            } else if let Some(y) = file.y.as_mut() {
                &mut y.limits
            } else {
                continue;
            };
            let fastest = piezo_core::fastest_invertible_slew_v_per_s(
                &model,
                limits.output_max_v - limits.output_min_v,
                period,
            );
            if fastest.is_finite() && fastest > 0.0 && fastest < limits.slew_limit_v_per_s {
                limits.slew_limit_v_per_s = fastest;
            }
        }
    }
    file
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json_keys as keys;
    use std::collections::BTreeSet;

    /// A rate-dependent gain whose slew limit is below the records' fastest command gets a note
    /// naming the file, the field and both speeds; without the gain, or with a slew limit at the
    /// records' speed, none.
    #[test]
    fn a_slew_limit_below_the_records_speed_is_noted_for_a_rate_gain() {
        let text = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/relaxing-stack-close-loop.toml"),
        )
        .unwrap();
        let mut file = StageFile::parse("stage.toml", &text).unwrap();
        let path = Path::new("out/stage.toml");
        assert!(slower_than_the_records(path, &file).is_empty());
        file.x.effects.hysteresis_rate_gain_s_per_v = 1e-5;
        file.x.limits.slew_limit_v_per_s = 3571.0;
        let reached = file.x.identified.as_ref().unwrap().input_rate_max_v_per_s;
        assert_eq!(reached, Some(22589.236));
        let notes = slower_than_the_records(path, &file);
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(
            notes[0].starts_with("out/stage.toml: `x.limits.slew_limit_v_per_s` = 3571 V/s")
                && notes[0].contains("`x.effects.hysteresis_rate_gain_s_per_v`")
                && notes[0].contains("reached 22589 V/s"),
            "{}",
            notes[0]
        );
        file.x.limits.slew_limit_v_per_s = 22589.236;
        assert!(slower_than_the_records(path, &file).is_empty());
    }

    /// A written file's report has the verdict's keys beside its own; a refusal carries the
    /// check's message and the remedy, and a file not written says why.
    #[test]
    fn a_written_stage_file_reports_its_verdict_beside_its_path() {
        let refused = WrittenStage {
            path: "out/stage.toml".into(),
            not_written: Some("read-only".into()),
            verdict: Verdict::Refused {
                kind: RefusalKind::NotInvertible,
                message: "stage.toml:30:1: `x.static_map`: not invertible".into(),
            },
        };
        let json = crate::to_json(&refused.report(false, None)).unwrap();
        assert_eq!(
            keys(&json),
            BTreeSet::from([
                "stage_file",
                "stage_file_written",
                "stage_file_not_written",
                "stage_file_check",
                "verdict",
                "refusal",
            ])
        );
        assert_eq!(json["stage_file"], "out/stage.toml");
        assert_eq!(json["stage_file_written"], false);
        assert_eq!(json["stage_file_not_written"], "read-only");
        assert_eq!(json["verdict"], "refused");
        assert_eq!(json["stage_file_check"], refused.verdict.words().as_str());
        assert_eq!(keys(&json["refusal"]), BTreeSet::from(["reason", "remedy"]));
        assert_eq!(
            json["refusal"]["reason"],
            "stage.toml:30:1: `x.static_map`: not invertible"
        );
        assert_eq!(
            json["refusal"]["remedy"],
            refused.verdict.remedy(false, None).unwrap().as_str()
        );

        let accepted = WrittenStage {
            not_written: None,
            verdict: Verdict::Accepted,
            ..refused
        };
        let json = crate::to_json(&accepted.report(true, None)).unwrap();
        assert_eq!(json["stage_file_written"], true);
        assert!(json["stage_file_not_written"].is_null());
        assert!(json["refusal"].is_null());
        assert_eq!(json["verdict"], "accepted");
        let verdict = crate::to_json(&Verdict::NotRunByFirmware.report(true, None)).unwrap();
        assert_eq!(
            keys(&verdict),
            BTreeSet::from(["stage_file_check", "verdict", "refusal"])
        );
        assert_eq!(verdict["verdict"], "not-run-by-firmware");
    }
}
