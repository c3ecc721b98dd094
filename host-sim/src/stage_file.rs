//! The stage file as the tools write it: `[stage]` and `[io]` carried over from an existing stage
//! file (`--stage FILE`), or made from the record with a placeholder io chain; the axes from the
//! fit. Reading, writing and validating are `piezo_stage`'s.

use piezo_stage::{Axis, Io, Stage, StageFile};
use std::path::Path;

/// The `[stage]` and `[io]` sections of a file about to be written: from `given` (an existing
/// stage file, read and validated) or, without one, named `name` at the record's rate
/// `record_rate_hz` with a placeholder io chain (said on stderr).
pub fn stage_and_io(
    given: Option<&Path>,
    name: &str,
    record_rate_hz: f64,
) -> Result<(Stage, Io), String> {
    match given {
        Some(path) => {
            let (file, _) = StageFile::load(path).map_err(|e| format!("--stage: {e}"))?;
            Ok((file.stage, file.io))
        }
        None => {
            eprintln!(
                "note: [io] is a placeholder (DAC8563 0-5 V, 24 V/V amplifier, ADS8681 ±10.24 V, \
                 10 µm/V sensor) and the loop rate is the record's ({record_rate_hz:.6} Hz): pass \
                 --stage FILE to carry [stage] and [io] from your stage file"
            );
            Ok((
                Stage {
                    name: name.to_string(),
                    version: "1".into(),
                    loop_rate_hz: rate_of(record_rate_hz),
                },
                Io::placeholder(),
            ))
        }
    }
}

/// A record's rate as a loop rate: rounded to 1 mHz, so that 1 / (mean sample period) reads as the
/// nominal rate (200 Hz, not 199.99999 Hz).
pub fn rate_of(record_rate_hz: f64) -> f32 {
    ((record_rate_hz * 1e3).round() / 1e3) as f32
}

/// Assembles, validates and writes a stage file; returns a one-line verdict on whether the
/// firmware's chain accepts it. `allow_refused`: write and report a set the firmware refuses
/// instead of failing. An axis's slew limit is lowered, where needed, to the fastest the core
/// accepts at the file's loop rate (a full-window move in `MIN_WINDOW_TICKS` ticks).
pub fn write_stage(
    path: &Path,
    header: &str,
    stage: Stage,
    io: Io,
    axes: Vec<Axis>,
    allow_refused: bool,
) -> Result<String, String> {
    let period = 1.0 / stage.loop_rate_hz;
    let axes: Vec<Axis> = axes
        .into_iter()
        .map(|mut a| {
            let l = &mut a.limits;
            let fastest = piezo_core::CompensatorSettings {
                output_min_v: l.output_min_v,
                output_max_v: l.output_max_v,
                slew_limit_v_per_s: l.slew_limit_v_per_s,
                sample_period_s: period,
            }
            .fastest_slew_v_per_s();
            if fastest.is_finite() && fastest > 0.0 {
                l.slew_limit_v_per_s = l.slew_limit_v_per_s.min(fastest);
            }
            a
        })
        .collect();
    let mut axes = axes.into_iter();
    let x = axes.next().ok_or("no axis to write")?;
    let file = StageFile {
        stage,
        io,
        x,
        y: axes.next(),
    };
    file.write(path, header)
        .map_err(|e| format!("--out: {e}"))?;
    let name = path.display().to_string();
    let firmware_runs = file.axes().iter().all(|(_, a)| a.model.runs_on_firmware());
    if !firmware_runs {
        return Ok("a model family the firmware does not run (it runs symmetric and asymmetric static models)".into());
    }
    match file.validate() {
        Ok(_) => Ok("accepted by the firmware's stage-file check".into()),
        Err(e) => {
            let text = std::fs::read_to_string(path).unwrap_or_default();
            let e = e.located(&name, &text);
            if allow_refused {
                Ok(format!("REFUSED by the firmware's stage-file check: {e}"))
            } else {
                Err(format!(
                    "the set written to {name} would be refused by the firmware: {e} \
                     (pass --allow-refused to keep it anyway, or --invertible to fit only sets the \
                     compensator accepts)"
                ))
            }
        }
    }
}
